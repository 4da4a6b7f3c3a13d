#!/usr/bin/env bash
# Prepare a runnable MDM (motion-diffusion-model, also holds DiP) checkout for smdm-plugin's
# integration tests and for training/sampling on a machine WITHOUT internet access.
#
#   SMDM_MDM_SRC=/path/to/motion-diffusion-model scripts/prepare_mdm_checkout.sh [DEST]
#
# SMDM_MDM_SRC  a git checkout of github:GuyTevet/motion-diffusion-model that you provide
#               (tested at d4fd88c). It is never modified.
# DEST          where the runnable copy goes (default: ./mdm_checkout). An existing DEST is
#               reused (only missing pieces are added).
# SMDM_HUMANML3D (optional) a HumanML3D-format data folder (new_joint_vecs/, texts/, Mean.npy,
#               Std.npy, train.txt ...); linked as DEST/dataset/HumanML3D when that is missing.
# SMDM_SKIP_PIP=1 skip the pip step.
#
# What it installs into the current Python (`python -m pip`), only what MDM's import paths
# for train.train_mdm / sample.generate / sample.edit / eval.eval_humanml need:
#   openai-clip (the `clip` module; installed --no-deps: its deps are listed below),
#   ftfy regex tqdm pillow, setuptools<81 if pkg_resources is missing (clip imports it),
#   torchvision pinned to the installed torch when such a wheel loads (see below), smplx, spacy (imported at module level by the HumanML3D loader), transformers (DiP's
#   DistilBERT), moviepy<2 (sample.generate imports moviepy.editor), blobfile, matplotlib,
#   scipy, h5py, pandas, joblib, wandb (train/train_platforms.py imports it at class
#   definition, so every entry point needs it; nothing is logged unless you ask).
#
# What it does NOT fetch (no internet): CLIP ViT-B/32 weights, DistilBERT, SMPL, GloVe and the
# T2M evaluators. See docs/mdm.md "Providing CLIP / DistilBERT / SMPL locally"; the integration
# tests use random-weight encoders of the right architecture instead.
set -euo pipefail

SRC="${SMDM_MDM_SRC:-}"
DEST="${1:-./mdm_checkout}"
PY="${PYTHON:-python}"

if [[ -z "$SRC" ]]; then
    echo "prepare_mdm_checkout: set SMDM_MDM_SRC to a git checkout of motion-diffusion-model" >&2
    exit 2
fi
if [[ ! -f "$SRC/model/mdm.py" || ! -f "$SRC/utils/model_util.py" ]]; then
    echo "prepare_mdm_checkout: SMDM_MDM_SRC=$SRC does not look like an MDM checkout (no model/mdm.py)" >&2
    exit 2
fi

# ---------------------------------------------------------------- 1. the copy
if [[ ! -f "$DEST/model/mdm.py" ]]; then
    mkdir -p "$(dirname "$DEST")"
    if [[ -d "$SRC/.git" ]] || git -C "$SRC" rev-parse --git-dir >/dev/null 2>&1; then
        # a local clone keeps git history, so `git apply` of patches/mdm.patch works in DEST
        git clone --quiet --no-hardlinks "$SRC" "$DEST"
        # carry uncommitted local changes of SRC as well? no: tests want upstream HEAD.
    else
        cp -a "$SRC" "$DEST"
    fi
    echo "prepare_mdm_checkout: copied $SRC -> $DEST ($(git -C "$DEST" rev-parse --short HEAD 2>/dev/null || echo no-git))"
else
    echo "prepare_mdm_checkout: $DEST already holds an MDM tree, reusing it"
fi

# ---------------------------------------------------------------- 2. data
if [[ -n "${SMDM_HUMANML3D:-}" && ! -e "$DEST/dataset/HumanML3D" ]]; then
    ln -s "$(cd "$SMDM_HUMANML3D" && pwd)" "$DEST/dataset/HumanML3D"
    echo "prepare_mdm_checkout: linked dataset/HumanML3D -> $SMDM_HUMANML3D"
fi

# ---------------------------------------------------------------- 3. python deps
if [[ "${SMDM_SKIP_PIP:-0}" != "1" ]]; then
    TORCH_VER="$("$PY" -c 'import torch; print(torch.__version__)' 2>/dev/null || true)"
    if [[ -z "$TORCH_VER" ]]; then
        echo "prepare_mdm_checkout: torch is not importable by $PY; install torch first" \
             "(a CPU build: pip install torch==<version> from your local wheel/index)" >&2
        exit 3
    fi
    CONSTRAINTS="$(mktemp)"
    trap 'rm -f "$CONSTRAINTS"' EXIT
    # never let pip replace the installed torch (a different torch pulls GBs of CUDA wheels)
    echo "torch==${TORCH_VER%%+*}" > "$CONSTRAINTS"
    TV_MISSING=""
    PIP=("$PY" -m pip install --quiet --disable-pip-version-check -c "$CONSTRAINTS")
    # `clip`: OpenAI CLIP is on PyPI as openai-clip (module name `clip`); --no-deps keeps pip
    # away from torch, its real deps are installed next.
    "$PY" -c 'import clip' 2>/dev/null || "${PIP[@]}" --no-deps openai-clip
    "${PIP[@]}" ftfy regex tqdm pillow
    # clip.py does `from pkg_resources import packaging`; setuptools >= 81 dropped pkg_resources
    "$PY" -c 'from pkg_resources import packaging' 2>/dev/null || "${PIP[@]}" "setuptools<81"
    "${PIP[@]}" smplx spacy transformers "moviepy<2" blobfile matplotlib scipy h5py pandas joblib wandb
    # torchvision: clip.py imports torchvision.transforms (image preprocessing only; MDM never
    # uses it). The constraint picks the torchvision whose torch pin equals the installed torch.
    # PyPI's Linux torchvision wheels are CUDA builds: next to a CPU-only torch their ops library
    # cannot load and `import torchvision` raises. Then it is removed again (a broken torchvision
    # also breaks transformers' imports) and `import clip` needs either the matching CPU wheel
    # (pip install torchvision==X --index-url <your CPU wheel index>) or the tiny stand-in that
    # the integration tests' harness uses (tests/integration/mdm_harness.py).
    if ! "$PY" -c 'import torchvision' 2>/dev/null; then
        "${PIP[@]}" torchvision || true
        if ! "$PY" -c 'import torchvision' 2>/dev/null; then
            echo "prepare_mdm_checkout: torchvision from PyPI does not load next to torch $TORCH_VER" \
                 "(CUDA build); uninstalling it. See docs/mdm.md." >&2
            "$PY" -m pip uninstall --quiet -y torchvision || true
            TV_MISSING=1
        fi
    fi
    TV_MISSING="${TV_MISSING:-}" "$PY" - <<'EOF'
import importlib, sys
import os
mods = ["smplx", "spacy", "transformers", "moviepy.editor", "blobfile",
        "matplotlib", "scipy", "ftfy"]
if not os.environ.get("TV_MISSING"):
    mods += ["torchvision", "clip"]
else:
    import importlib.util
    if importlib.util.find_spec("clip") is None:
        mods.append("clip")
bad = []
for m in mods:
    try:
        importlib.import_module(m)
    except Exception as e:  # noqa: BLE001
        bad.append(f"{m}: {type(e).__name__}: {e}")
if bad:
    print("prepare_mdm_checkout: these imports still fail:\n  " + "\n  ".join(bad), file=sys.stderr)
    sys.exit(4)
import torch
print(f"prepare_mdm_checkout: python deps OK (torch {torch.__version__})")
EOF
fi

# ---------------------------------------------------------------- 4. what is still missing
missing=()
[[ -e "$DEST/dataset/HumanML3D/new_joint_vecs" ]] || missing+=("dataset/HumanML3D (set SMDM_HUMANML3D or link it)")
[[ -e "$DEST/glove/our_vab_data.npy" ]] || missing+=("glove/ (GloVe vocab for the T2M evaluator word vectors; tests write a stub)")
[[ -e "$DEST/body_models/smpl/SMPL_NEUTRAL.pkl" ]] || missing+=("body_models/smpl/SMPL_NEUTRAL.pkl (MDM builds SMPL at model init)")
[[ -e "$DEST/t2m/text_mot_match/model/finest.tar" ]] || missing+=("t2m/ evaluators (eval.eval_humanml only)")
if ((${#missing[@]})); then
    echo "prepare_mdm_checkout: not present (fine for the integration tests, see docs/mdm.md):"
    printf '  - %s\n' "${missing[@]}"
fi
echo "prepare_mdm_checkout: ready: $DEST"
