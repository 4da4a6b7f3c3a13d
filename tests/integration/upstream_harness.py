"""Run an upstream script (priorMDM / MotionDiffuse) offline on CPU, in a subprocess:

    python upstream_harness.py REPO_DIR SCRIPT_OR_-m_MODULE [args...]

Only the *harness* is changed, never upstream files:

* ``clip.load`` returns a randomly initialised CLIP of the requested architecture (ViT-B/32:
  the weights cannot be downloaded here); ``torchvision`` is stubbed when missing (CLIP's
  image preprocessing is never used for text encoding);
* ``spacy`` / ``cv2`` / ``mmcv`` are stubbed when missing (imported by upstream files but not
  used on these code paths, or only for single-process distributed helpers);
* priorMDM: ``model.rotation2xyz.Rotation2xyz`` is replaced by a stand-in that needs no SMPL
  body model files (HumanML3D samples are already joint positions, ``pose_rep='xyz'``);
* on CPU-only torch, ``Module.cuda`` / ``Tensor.cuda`` return ``self`` and
  ``torch.cuda.set_device`` is a no-op (MotionDiffuse's tools call them unconditionally);
* on CPU-only torch, ``clip.model.convert_weights`` (fp16) is a no-op: fp16 matmuls are very slow
  on CPU and the fake CLIP's weights are random anyway;
* ``SMDM_CLIP_LAYERS=n``: the fake CLIP's text transformer has ``n`` layers instead of 12 (width
  512 and output 512 are kept, as both upstreams need them; the unused vision tower shrinks to
  one small layer), so CPU tests are not dominated by text encoding;
* ``SMDM_HOOKS=priormdm|motiondiffuse`` installs the plugin's import hooks instead of the patch;
* ``SMDM_NO_ANOMALY=1``: ``torch.autograd.set_detect_anomaly`` becomes a no-op (MotionDiffuse's
  ``tools/train.py`` turns anomaly detection on, which makes every CPU backward several seconds
  slower; runs that keep it check that no backward op yields NaN);
* ``SMDM_SEED=n`` seeds ``random``, ``numpy`` and ``torch`` before the script runs (MotionDiffuse
  seeds nothing; priorMDM seeds itself);
* ``SMDM_RECORD=path``: every training keyframe mask the plugin computes (``MaskSchedule.training_mask``,
  ``training_plan``),
  every sampling call's plan (``adapters.call.keyframe_plan``), every mask handed to a ``KeyframeTransformer`` and, for MotionDiffuse, the
  number of tokens entering the first decoder block (with that call's mask) is recorded, with the
  sequence lengths, and pickled to ``path`` at exit, for the tests to check.
"""
from __future__ import annotations

import os
import runpy
import sys
import types


def _stub(name: str, **attrs) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__dict__.update(attrs)
    mod.__path__ = []  # a package, so submodules can be stubbed too
    sys.modules[name] = mod
    return mod


def _have(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


class _Any:
    def __init__(self, *a, **k):
        pass

    def __call__(self, x, *a, **k):
        return x


def install_fake_clip() -> None:
    if not _have("torchvision"):
        tv = _stub("torchvision")
        tv.transforms = _stub("torchvision.transforms", Compose=_Any, Resize=_Any, CenterCrop=_Any,
                              ToTensor=_Any, Normalize=_Any)
        tv.transforms.InterpolationMode = types.SimpleNamespace(BICUBIC=3)
    import clip
    from clip.model import CLIP

    archs = {  # embed_dim, image_resolution, vision_layers, vision_width, patch, ctx, vocab, width, heads, layers
        "ViT-B/32": (512, 224, 12, 768, 32, 77, 49408, 512, 8, 12),
        "ViT-B/16": (512, 224, 12, 768, 16, 77, 49408, 512, 8, 12),
    }

    layers = int(os.environ.get("SMDM_CLIP_LAYERS", "0") or 0)

    def load(name, device="cpu", jit=False, download_root=None):
        import torch

        torch.manual_seed(1234)
        arch = list(archs[name])
        if layers > 0:  # text: `layers` layers of width 512; vision (unused): 1 layer, width 64
            arch[9], arch[2], arch[3] = layers, 1, 64
        model = CLIP(*arch).to(device).eval()  # random weights, right (text) architecture
        return model, _Any()

    clip.load = load
    clip.available_models = lambda: list(archs)
    import torch

    if not torch.cuda.is_available():
        import clip.model

        clip.model.convert_weights = lambda model: None  # fp16 on CPU: slow, and pointless here


def install_stubs() -> None:
    import numpy as np
    import torch

    for alias, typ in (("float", float), ("int", int), ("bool", bool)):  # removed in numpy >= 1.24
        if alias not in np.__dict__:
            setattr(np, alias, typ)

    if not _have("spacy"):
        _stub("spacy", load=lambda *a, **k: None)
    else:  # the en_core_web_sm model is not on PyPI: fall back to a blank English pipeline
        import spacy

        _load = spacy.load

        def load(name, *a, **k):
            try:
                return _load(name, *a, **k)
            except OSError:
                return spacy.blank("en")

        spacy.load = load
    if not _have("cv2"):
        _stub("cv2", norm=lambda *a, **k: 0.0)
    if not _have("mmcv"):
        mm = _stub("mmcv")
        mm.runner = _stub("mmcv.runner", get_dist_info=lambda: (0, 1), init_dist=lambda *a, **k: None)

        class _DP(torch.nn.Module):
            def __init__(self, module, *a, **k):
                super().__init__()
                self.module = module

            def forward(self, *a, **k):
                return self.module(*a, **k)

        mm.parallel = _stub("mmcv.parallel", MMDistributedDataParallel=_DP, MMDataParallel=_DP,
                            collate=None)

        class Registry:
            def __init__(self, *a, **k):
                pass

        mm.utils = _stub("mmcv.utils", Registry=Registry, build_from_cfg=lambda *a, **k: None)
    if not torch.cuda.is_available():
        torch.nn.Module.cuda = lambda self, *a, **k: self
        torch.Tensor.cuda = lambda self, *a, **k: self
        torch.cuda.set_device = lambda *a, **k: None


def install_priormdm_stubs() -> None:
    import model.rotation2xyz as r2x

    class Rotation2xyz:
        """No SMPL files needed: HumanML3D motion (hml_vec) is converted with pose_rep='xyz'."""

        def __init__(self, device="cpu", dataset="amass", batch_size=None):
            self.smpl_model = torch.nn.Identity()

        def __call__(self, x, mask, pose_rep, *a, **k):
            if pose_rep == "xyz":
                return x
            raise NotImplementedError("harness: SMPL body model not available")

    import torch

    r2x.Rotation2xyz = Rotation2xyz
    if os.environ.get("SMDM_NO_PLOT"):  # no ffmpeg here: skip the mp4 rendering
        import data_loaders.humanml.utils.plot_script as ps

        ps.plot_3d_motion = lambda *a, **k: None


def install_recorder(path: str) -> None:
    """``SMDM_RECORD=path``: record the keyframe masks (see the module docstring)."""
    import atexit
    import pickle

    import torch

    from smdm_plugin.core.keyframe_transformer import KeyframeTransformer
    from smdm_plugin.core.schedule import MaskSchedule, resolve_lengths

    records = []

    def record_training(mask, lengths, forced):
        B, N = mask.shape
        lengths = resolve_lengths(lengths, B, N, mask.device)
        records.append({"kind": "train", "mask": mask.detach().cpu().numpy().copy(),
                        "lengths": lengths.detach().cpu().numpy().copy(),
                        "forced": None if forced is None else
                        torch.as_tensor(forced).detach().cpu().bool().numpy().copy()})

    def training_mask(original):
        def method(self, x, *a, **k):
            mask = original(self, x, *a, **k)
            record_training(mask, a[0] if a else k.get("lengths"),        # (lengths, forced, ...)
                            a[1] if len(a) > 1 else k.get("forced"))
            return mask
        return method

    def training_plan(original):
        # (the mask and its plan in one op: no forced frames; None when the schedule cannot)
        def method(self, x, *a, **k):
            made = original(self, x, *a, **k)
            if made is not None:
                record_training(made[0], a[0] if a else k.get("lengths"), None)
            return made
        return method

    MaskSchedule.training_mask = training_mask(MaskSchedule.training_mask)
    MaskSchedule.training_plan = training_plan(MaskSchedule.training_plan)
    import smdm_plugin.adapters.call as call
    original_plan = call.keyframe_plan

    def keyframe_plan(state, frames, timesteps, lengths, forced, mask=None, *a, **k):
        # every sampling call's plan (a sampling loop makes it once and looks it up: record each call)
        plan = original_plan(state, frames, timesteps, lengths, forced, mask, *a, **k)
        if mask is None:
            prefix = int(state.variant.prefix_len)
            records.append({"kind": "sample", "mask": plan.mask[:, prefix:].detach().cpu().numpy().copy(),
                            "lengths": lengths.detach().cpu().numpy().copy(),
                            "forced": None if forced is None else forced.detach().cpu().bool().numpy().copy()})
        return plan

    call.keyframe_plan = keyframe_plan
    original_set = KeyframeTransformer.set_plan

    def set_plan(self, plan):  # every call's keyframes reach the transformer as a KeyframePlan
        if plan is not None:
            records.append({"kind": "transformer", "mask": plan.mask.detach().cpu().numpy().copy(),
                            "lengths": None, "forced": None})
        return original_set(self, plan)

    KeyframeTransformer.set_plan = set_plan

    # MotionDiffuse: the tokens that reach the decoder blocks, with the mask of that call
    import smdm_plugin.families.motiondiffuse.model as md_adapter

    import smdm_plugin.adapters.surgery as surgery

    original_sparsify = surgery.sparsify

    def sparsify_motiondiffuse(model, *a, **k):
        out = original_sparsify(model, *a, **k)
        blocks = getattr(model, "temporal_decoder_blocks", None)
        if not md_adapter.MotionDiffuseFamily().matches(model):
            return out
        if blocks is not None and len(blocks) and not getattr(model, "_smdm_recorded", False):
            model._smdm_recorded = True

            def pre_hook(module, args):
                mask = getattr(getattr(getattr(model, "_smdm_state", None), "family_state", None), "last_mask", None)
                records.append({"kind": "blocks", "tokens": int(args[0].shape[1]),
                                "mask": None if mask is None else mask.detach().cpu().numpy().copy(),
                                "lengths": None, "forced": None})

            blocks[0].register_forward_pre_hook(pre_hook)
        return out

    surgery.sparsify = sparsify_motiondiffuse

    def dump():
        with open(path, "wb") as f:
            pickle.dump(records, f)
        print(f"SMDM_RECORD {len(records)} masks -> {path}", flush=True)

    atexit.register(dump)


def main() -> None:
    repo, target, *argv = sys.argv[1:]
    os.chdir(repo)
    sys.path.insert(0, os.getcwd())
    install_stubs()
    install_fake_clip()
    hooks = os.environ.get("SMDM_HOOKS", "")
    if hooks:
        from smdm_plugin.integrations.checkouts import INTEGRATIONS

        INTEGRATIONS.get(hooks).install_hooks()   # the family's integration, by its name
    if os.environ.get("SMDM_RECORD"):
        install_recorder(os.environ["SMDM_RECORD"])
    if os.path.exists(os.path.join(repo, "model", "rotation2xyz.py")):
        install_priormdm_stubs()
    if os.environ.get("SMDM_NO_PLOT") and os.path.exists(os.path.join(repo, "utils", "plot_script.py")):
        import utils.plot_script as ps  # MotionDiffuse: old matplotlib 3D animation code

        ps.plot_3d_motion = lambda *a, **k: None
    if os.environ.get("SMDM_NO_ANOMALY"):
        import torch

        torch.autograd.set_detect_anomaly = lambda *a, **k: None
    if os.environ.get("SMDM_SEED"):
        import random

        import numpy as np
        import torch

        seed = int(os.environ["SMDM_SEED"])
        random.seed(seed)
        np.random.seed(seed)
        torch.manual_seed(seed)
    if target == "-m":
        module, *argv = argv
        sys.argv = [module] + argv
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    else:
        sys.argv = [target] + argv
        sys.path.insert(0, os.path.dirname(os.path.abspath(target)))
        runpy.run_path(target, run_name="__main__")


if __name__ == "__main__":
    main()
