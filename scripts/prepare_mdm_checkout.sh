#!/usr/bin/env bash
# Prepare a runnable MDM (motion-diffusion-model, also holds DiP) checkout for smdm-plugin: the
# steps pip cannot do. The Python packages MDM imports come from the extra instead:
#
#   pip install "smdm-plugin[mdm]"          # or: pip install "/path/to/smdm-plugin[mdm]"
#   SMDM_MDM_SRC=/path/to/motion-diffusion-model scripts/prepare_mdm_checkout.sh [DEST]
#
# SMDM_MDM_SRC    a git checkout of github:GuyTevet/motion-diffusion-model that you provide
#                 (tested at d4fd88c). It is never modified.
# DEST            where the runnable copy goes (default: ./mdm_checkout). An existing DEST is
#                 reused (only missing pieces are added).
# SMDM_HUMANML3D  (optional) a HumanML3D-format data folder (new_joint_vecs/, texts/, Mean.npy,
#                 Std.npy, train.txt ...); linked as DEST/dataset/HumanML3D when that is missing.
# SMDM_APPLY_PATCH=1 (optional) `git apply` smdm-plugin's patches/mdm.patch in DEST (the patch
#                 route; without it, use `smdm run --repo DEST -- ...`).
# PYTHON          the interpreter to check (default: python): it reports what MDM's entry points
#                 cannot import, and the pip command that installs it. It installs nothing.
#
# Not fetched (no internet assumed): CLIP ViT-B/32 weights, DistilBERT, SMPL, GloVe and the T2M
# evaluators; see docs/mdm.md "Providing CLIP / DistilBERT / SMPL locally".
set -euo pipefail

SRC="${SMDM_MDM_SRC:-}"
DEST="${1:-./mdm_checkout}"
PY="${PYTHON:-python}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
PATCH="$HERE/../patches/mdm.patch"

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
    if git -C "$SRC" rev-parse --git-dir >/dev/null 2>&1; then
        # a local clone of upstream HEAD keeps git history, so `git apply` works in DEST
        git clone --quiet --no-hardlinks "$SRC" "$DEST"
    else
        cp -a "$SRC" "$DEST"
    fi
    echo "prepare_mdm_checkout: copied $SRC -> $DEST ($(git -C "$DEST" rev-parse --short HEAD 2>/dev/null || echo no-git))"
else
    echo "prepare_mdm_checkout: $DEST already holds an MDM tree, reusing it"
fi

# ---------------------------------------------------------------- 2. the patch (optional)
if [[ "${SMDM_APPLY_PATCH:-0}" == "1" ]]; then
    if (cd "$DEST" && git apply --reverse --check "$PATCH" 2>/dev/null); then
        echo "prepare_mdm_checkout: patches/mdm.patch already applied"
    else
        (cd "$DEST" && git apply "$PATCH")
        echo "prepare_mdm_checkout: applied patches/mdm.patch"
    fi
fi

# ---------------------------------------------------------------- 3. data
if [[ -n "${SMDM_HUMANML3D:-}" && ! -e "$DEST/dataset/HumanML3D" ]]; then
    ln -s "$(cd "$SMDM_HUMANML3D" && pwd)" "$DEST/dataset/HumanML3D"
    echo "prepare_mdm_checkout: linked dataset/HumanML3D -> $SMDM_HUMANML3D"
fi

# ---------------------------------------------------------------- 4. report
if ! "$PY" - <<'EOF'
import importlib, sys
mods = ["torch", "clip", "smplx", "spacy", "transformers", "moviepy.editor", "blobfile", "matplotlib",
        "scipy", "joblib", "wandb", "PIL", "smdm_plugin"]
bad = []
for m in mods:
    try:
        importlib.import_module(m)
    except Exception as e:  # noqa: BLE001 - report every failure
        bad.append(f"{m}: {type(e).__name__}: {e}")
if bad:
    print("prepare_mdm_checkout: this Python cannot import what MDM needs:\n  " + "\n  ".join(bad)
          + '\n  install them with: pip install "smdm-plugin[mdm]"  (see docs/mdm.md for torchvision)',
          file=sys.stderr)
    sys.exit(1)
print("prepare_mdm_checkout: python packages OK")
EOF
then
    echo "prepare_mdm_checkout: (the checkout itself is ready)" >&2
fi
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
