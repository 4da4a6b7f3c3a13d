"""MDM's own ``sample.edit --edit_mode in_between`` with a sparse checkpoint, with the real upstream code:
the frames the edit keeps reach the sparse model as forced keyframes (``ends`` policy: the first and
last frame and the two seams of the generated gap), those frames are keyframe tokens at every step,
and MDM's imputation brings them out exact — through ``smdm run`` (the hook in
``smdm_plugin.families.mdm.upstream_edit``) and through the patch plus the two lines
``mdm_edit.add_forced_keyframes`` documents for ``sample/edit.py``.

Skipped unless ``SMDM_MDM_ROOT`` points at an MDM checkout (read-only: copied). CLIP has random weights
(``mdm_harness.py``); a tiny sparse trans_enc is trained for a few steps, enough to sample from.
"""
from __future__ import annotations

import json
import os
import re
import sys

import numpy as np
import pytest

from _upstream import PATCHES, plugin_env, run_logged

ROOT = os.environ.get("SMDM_MDM_ROOT")
HERE = os.path.dirname(os.path.abspath(__file__))
HARNESS = os.path.join(HERE, "mdm_harness.py")
ENV = {"SMDM_TEST_CLIP_LAYERS": "1", "SMDM_TEST_NUM_WORKERS": "0", "SMDM_TEST_NO_RENDER": "1"}
TINY = ["--dataset", "humanml", "--latent_dim", "64", "--layers", "2", "--batch_size", "8",
        "--save_interval", "1000000", "--seed", "10", "--diffusion_steps", "10"]
EDIT_LINES = ("    from smdm_plugin.families.mdm.upstream_edit import add_forced_keyframes  # sMDM: kept frames are keyframes\n"
              "    add_forced_keyframes(model, model_kwargs)\n")

pytestmark = pytest.mark.skipif(not ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")

PROBE = r"""
import json, sys
import torch
ckpt, out_dir = sys.argv[1], sys.argv[2]
sys.argv = ["sample.edit", "--model_path", ckpt, "--output_dir", out_dir, "--num_samples", "2",
            "--num_repetitions", "1", "--edit_mode", "in_between", "--text_condition", "a person walks"]
import sample.edit as edit
import diffusion.gaussian_diffusion as gd
from smdm_plugin.adapters.state import find_sparse_model, get_state

seen = {"masks": [], "forced": None, "steps": 0}
load = edit.load_saved_model
def load_saved_model(model, *a, **k):
    res = load(model, *a, **k)
    sparse = find_sparse_model(model)
    seen["sparse"] = sparse is not None
    if sparse is not None:
        sparse.register_forward_pre_hook(lambda m, args: seen["masks"].append(get_state(m).plan.mask.clone()))
    return res
edit.load_saved_model = load_saved_model

pmv = gd.GaussianDiffusion.p_mean_variance
def p_mean_variance(self, model, x, t, *a, model_kwargs=None, **k):
    y = model_kwargs["y"]
    seen["steps"] += 1
    if "smdm_keyframes" in y and y["smdm_keyframes"].forced is not None:
        seen["forced"] = y["smdm_keyframes"].forced.cpu().numpy().tolist()
    seen["lengths"] = y["lengths"].cpu().numpy().tolist()
    return pmv(self, model, x, t, *a, model_kwargs=model_kwargs, **k)
gd.GaussianDiffusion.p_mean_variance = p_mean_variance

loop = gd.GaussianDiffusion.p_sample_loop
def p_sample_loop(self, model, shape, *a, **k):
    out = loop(self, model, shape, *a, **k)
    y = k["model_kwargs"]["y"]
    keep = y["inpainting_mask"].all(dim=1).all(dim=1)  # [B, N] frames kept whole
    seen["kept_exact"] = bool(torch.equal(out.permute(0, 3, 1, 2)[keep], y["inpainted_motion"].permute(0, 3, 1, 2)[keep]))
    return out
gd.GaussianDiffusion.p_sample_loop = p_sample_loop

edit.main()
masks = torch.stack(seen.pop("masks"))  # [calls, B, N]
forced = torch.tensor(seen["forced"], dtype=torch.bool) if seen["forced"] is not None else None
seen["forced_in_every_mask"] = bool(masks[:, forced].all()) if forced is not None else None
seen["calls"] = len(masks)
seen["mask_sizes"] = masks.sum(-1)[-1].tolist()
print("EDIT=" + json.dumps(seen))
"""


def harness(repo, code, args, launcher, env=None):
    cmd = [sys.executable, HARNESS, "-c", code, *args]
    if launcher:
        cmd = [sys.executable, "-m", "smdm_plugin.integrations.launcher", "--repo", repo, "--"] + cmd
    return run_logged(cmd, cwd=repo, env=plugin_env({**ENV, **(env or {})}))


@pytest.fixture(scope="module")
def repos(upstream_copy):
    pristine = upstream_copy(ROOT, "mdm_edit_pristine")
    patched = upstream_copy(ROOT, "mdm_edit_patched", patch=os.path.join(PATCHES, "mdm.patch"))
    edit_py = os.path.join(patched, "sample", "edit.py")
    src = open(edit_py).read()
    anchor = "    all_motions = []\n"
    assert src.count(anchor) == 1, "sample/edit.py changed upstream: the patch lines need a new anchor"
    if EDIT_LINES not in src:
        with open(edit_py, "w") as f:
            f.write(src.replace(anchor, EDIT_LINES + anchor))
    return {"launcher": pristine, "patch": patched}


@pytest.fixture(scope="module")
def sparse_ckpt(repos, tmp_path_factory):
    save = str(tmp_path_factory.mktemp("edit_runs") / "sparse")
    cmd = [sys.executable, HARNESS, "train.train_mdm", "--save_dir", save, "--num_steps", "4", *TINY, "--sparse"]
    run_logged(cmd, cwd=repos["patch"], env=plugin_env(ENV))
    ckpts = sorted(f for f in os.listdir(save) if f.startswith("model") and f.endswith(".pt"))
    assert ckpts, os.listdir(save)
    return os.path.join(save, ckpts[-1])


@pytest.mark.parametrize("route", ["launcher", "patch"])
def test_edit_in_between_forces_the_seams_of_a_sparse_model(route, repos, sparse_ckpt, tmp_path):
    out_dir = str(tmp_path / "edit")
    proc = harness(repos[route], PROBE, [sparse_ckpt, out_dir], launcher=route == "launcher")
    seen = json.loads(re.search(r"EDIT=(.*)", proc.stdout).group(1))
    assert seen["sparse"] is True and seen["steps"] == 10
    for b, L in enumerate(seen["lengths"]):  # MDM's in_between: prefix_end 0.25, suffix_start 0.75
        ends = [0, int(0.25 * L) - 1, int(0.75 * L), L - 1]
        assert [n for n, f in enumerate(seen["forced"][b]) if f] == ends
    assert seen["forced_in_every_mask"] is True and seen["calls"] == 2 * seen["steps"]  # CFG: two calls a step
    # the budget stays the model's: ~20% of the valid frames plus at most the four seams
    for size, L in zip(seen["mask_sizes"], seen["lengths"]):
        assert size <= round(0.2 * L) + 4
    assert seen["kept_exact"] is True
    res = np.load(os.path.join(out_dir, "results.npy"), allow_pickle=True).item()
    assert res["motion"].shape == (2, 22, 3, 196) and np.isfinite(res["motion"]).all()
    # the edit says how it was made: the checkpoint's config beside results.npy
    ckpt_cfg = json.load(open(os.path.join(os.path.dirname(sparse_ckpt), "sparse_config.json")))
    assert json.load(open(os.path.join(out_dir, "sparse_config.json"))) == ckpt_cfg


def test_policy_from_the_environment(repos, sparse_ckpt, tmp_path):
    proc = harness(repos["launcher"], PROBE, [sparse_ckpt, str(tmp_path / "edit")], launcher=True,
                   env={"SMDM_EDIT_FORCED": "none"})
    seen = json.loads(re.search(r"EDIT=(.*)", proc.stdout).group(1))
    assert seen["forced"] is not None and not any(any(row) for row in seen["forced"])
    assert seen["kept_exact"] is True
