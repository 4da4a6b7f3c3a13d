"""Run an MDM entry point offline, for smdm-plugin's integration tests.

    cd <MDM checkout> && python <this file> train.train_mdm --save_dir ... [MDM args]
    cd <MDM checkout> && python <this file> -c "python code run after the stubs are installed"

MDM downloads or reads at run time things this machine does not have: CLIP ViT-B/32 weights
(``clip.load``), DistilBERT (DiP, ``transformers.from_pretrained``), the SMPL body model (built by
``Rotation2xyz`` at every model init, never used for the ``hml_vec`` HumanML3D representation)
and GloVe vectors (the T2M evaluator's word vectors, read by the HumanML3D loader). This harness
replaces each one that is missing, in memory only (upstream files are never touched):

* CLIP: a ``clip.model.CLIP`` with the ViT-B/32 text-tower hyper-parameters (width 512, 12
  layers, 8 heads, context 77, vocab 49408, embed dim 512) and random weights from a fixed seed;
  the vision tower, which MDM never calls, is shrunk; ``SMDM_TEST_CLIP_LAYERS`` lowers the
  text depth for speed (the tests use 1: a 12-layer text tower costs seconds per step here). The real tokenizer (shipped in the
  ``openai-clip`` package) is used. Real weights are used when ``~/.cache/clip/ViT-B-32.pt``
  exists, unless ``SMDM_TEST_RANDOM_ENCODERS=1``.
* DistilBERT: ``DistilBertModel(DistilBertConfig())`` (distilbert-base-uncased architecture) with
  random weights from a fixed seed, and a WordPiece tokenizer over a character vocabulary.
* SMPL: a parameter-free module, when ``body_models/smpl/SMPL_NEUTRAL.pkl`` is missing.
* GloVe: a vocabulary of only ``unk`` (all words map to it), when ``glove/`` is missing.

The global torch RNG is not consumed by these stubs, so seeded runs match upstream's RNG stream.
Also, for speed on 2 cores: DataLoaders use ``SMDM_TEST_NUM_WORKERS`` workers (default 0) and
``SMDM_TEST_NO_RENDER=1`` (default) skips the mp4 rendering of ``sample.generate``/``sample.edit``
(``results.npy`` is still written).
"""
from __future__ import annotations

import os
import runpy
import sys

CLIP_VIT_B32_TEXT = dict(embed_dim=512, context_length=77, vocab_size=49408,
                         transformer_width=512, transformer_heads=8, transformer_layers=12)
STUB_SEED = 1234


def _env_flag(name: str, default: str = "0") -> bool:
    return os.environ.get(name, default).strip().lower() in ("1", "true", "yes", "on")


def _force_random() -> bool:
    return _env_flag("SMDM_TEST_RANDOM_ENCODERS", "0")


def _random_clip():
    import torch
    import clip.model

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(STUB_SEED)
        hp = dict(CLIP_VIT_B32_TEXT)
        # SMDM_TEST_CLIP_LAYERS: fewer text layers for speed on small CPUs (default: ViT-B/32's 12)
        hp["transformer_layers"] = int(os.environ.get("SMDM_TEST_CLIP_LAYERS", hp["transformer_layers"]))
        model = clip.model.CLIP(image_resolution=32, vision_layers=1, vision_width=64,
                                vision_patch_size=32, **hp)
    return model


def _import_clip():
    """``import clip``; when torchvision cannot be imported (missing, or PyPI's Linux torchvision
    wheel, a CUDA build that does not load next to a CPU-only torch), ``clip.clip``'s import of
    ``torchvision.transforms`` (image preprocessing, never used by MDM) is served by placeholders
    that exist only while ``clip`` is imported: they are taken out of ``sys.modules`` afterwards,
    so other libraries (transformers) still see no torchvision."""
    import importlib.util
    import types

    try:
        import clip
        return clip
    except ImportError as e:
        if "torchvision" not in str(e):
            raise
    except RuntimeError as e:  # a torchvision build that does not match torch (CUDA wheel, CPU torch)
        if "torchvision" not in str(e):
            raise
    for name in [m for m in sys.modules if m in ("clip", "torchvision") or m.startswith(("clip.", "torchvision."))]:
        del sys.modules[name]

    class _Unavailable:
        def __init__(self, *a, **k):
            pass

        def __call__(self, *a, **k):
            raise RuntimeError("torchvision is not available (smdm-plugin test placeholder)")

    tv = types.ModuleType("torchvision")
    tr = types.ModuleType("torchvision.transforms")
    for n in ("Compose", "Resize", "CenterCrop", "ToTensor", "Normalize"):
        setattr(tr, n, type(n, (_Unavailable,), {}))
    tr.InterpolationMode = types.SimpleNamespace(BICUBIC=3, BILINEAR=2, NEAREST=0)
    tv.transforms = tr
    saved = {k: sys.modules.get(k) for k in ("torchvision", "torchvision.transforms")}
    sys.modules["torchvision"], sys.modules["torchvision.transforms"] = tv, tr
    try:
        import clip
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    assert importlib.util.find_spec("clip") is not None
    return clip


def install_clip_stub() -> None:
    clip = _import_clip()

    real_load = clip.load
    cache = os.path.expanduser("~/.cache/clip/ViT-B-32.pt")

    def load(name, device="cpu", jit=False, download_root=None):
        if name == "ViT-B/32" and (_force_random() or not os.path.exists(cache)):
            model = _random_clip().to(device)
            if str(device) == "cpu":
                model.float()  # as clip.load does on CPU
            return model, None
        return real_load(name, device=device, jit=jit, download_root=download_root)

    clip.load = load
    import clip.clip as clip_clip
    clip_clip.load = load


def _char_vocab_file() -> str:
    import string
    import tempfile

    tokens = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"]
    chars = string.ascii_lowercase + string.digits + string.punctuation
    tokens += list(chars) + ["##" + c for c in chars]
    fd, path = tempfile.mkstemp(prefix="smdm_vocab_", suffix=".txt")
    with os.fdopen(fd, "w") as f:
        f.write("\n".join(tokens) + "\n")
    return path


def install_bert_stub() -> None:
    import model.BERT.BERT_encoder as be

    real_init = be.BERT.__init__

    def init(self, modelpath):
        hub = os.environ.get("HF_HOME", os.path.expanduser("~/.cache/huggingface"))
        have_local = os.path.isdir(modelpath) or os.path.isdir(
            os.path.join(hub, "hub", "models--" + modelpath.replace("/", "--")))
        if have_local and not _force_random():
            return real_init(self, modelpath)
        import torch
        from transformers import DistilBertConfig, DistilBertModel, DistilBertTokenizer
        torch.nn.Module.__init__(self)
        os.environ["TOKENIZERS_PARALLELISM"] = "false"
        self.tokenizer = DistilBertTokenizer(vocab_file=_char_vocab_file(), do_lower_case=True)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(STUB_SEED)
            self.text_model = DistilBertModel(DistilBertConfig())

    be.BERT.__init__ = init


def install_smpl_stub() -> None:
    if os.path.exists("body_models/smpl/SMPL_NEUTRAL.pkl"):
        return
    import torch.nn as nn
    import model.rotation2xyz as r2x

    class NoSMPL(nn.Module):
        """Stands in for SMPL (unused by hml_vec); has no parameters or buffers."""

        def forward(self, *args, **kwargs):  # pragma: no cover - never called for hml_vec
            raise RuntimeError("SMPL body model is not available (smdm-plugin test stub)")

    r2x.SMPL = NoSMPL


def install_glove_stub() -> None:
    if os.path.exists(os.path.join("glove", "our_vab_data.npy")):
        return
    import numpy as np
    import data_loaders.humanml.utils.word_vectorizer as wv

    def init(self, meta_root, prefix):
        self.word2vec = {"unk": np.zeros(300, dtype=np.float32)}

    wv.WordVectorizer.__init__ = init


def install_loader_workers() -> None:
    n = int(os.environ.get("SMDM_TEST_NUM_WORKERS", "0"))
    import functools
    import torch.utils.data as tud
    import data_loaders.get_data as gd

    class DataLoader(tud.DataLoader):
        def __init__(self, *args, **kwargs):
            kwargs["num_workers"] = n
            super().__init__(*args, **kwargs)

    gd.DataLoader = DataLoader
    del functools


def install_no_render() -> None:
    if not _env_flag("SMDM_TEST_NO_RENDER", "1"):
        return
    import data_loaders.humanml.utils.plot_script as ps

    def plot_3d_motion(save_path, *args, **kwargs):
        return None

    ps.plot_3d_motion = plot_3d_motion
    import sample.generate as gen

    def save_multiple_samples(*args, **kwargs):
        return None

    gen.plot_3d_motion = plot_3d_motion
    gen.save_multiple_samples = save_multiple_samples


def install_ddp_probe() -> None:
    """``SMDM_TEST_DDP_PROBE=DIR`` (training under ``torchrun``): each rank writes ``DIR/rank<r>.pt``
    (its model's state dict when ``TrainLoop.run_loop`` ends) and, at exit, ``DIR/rank<r>.json``:
    ``writes``, every file the process opened for writing (a ``sys.addaudithook`` on ``open``, so
    nothing escapes it), and ``epochs``, the dataset indices each pass over a ``DistributedSampler``
    yielded. Read-only otherwise: it changes nothing the run computes."""
    out = os.environ.get("SMDM_TEST_DDP_PROBE")
    if not out:
        return
    import atexit
    import json

    import torch
    import torch.utils.data as tud

    rank = os.environ.get("RANK", "0")
    record = {"writes": [], "epochs": []}
    write_flags = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND

    def audit(event, args):
        if event != "open" or not isinstance(args[0], (str, bytes, os.PathLike)):
            return
        path, mode, flags = args
        if (isinstance(mode, str) and any(c in mode for c in "wax+")) or (isinstance(flags, int) and flags & write_flags):
            record["writes"].append(os.path.abspath(os.fsdecode(path)))

    sys.addaudithook(audit)
    sampler_iter = tud.DistributedSampler.__iter__

    def __iter__(self):
        indices = list(sampler_iter(self))
        record["epochs"].append(indices)
        return iter(indices)

    tud.DistributedSampler.__iter__ = __iter__
    import train.training_loop as tl

    run_loop = tl.TrainLoop.run_loop

    def run_loop_and_dump(self, *args, **kwargs):
        try:
            return run_loop(self, *args, **kwargs)
        finally:
            torch.save({k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                       os.path.join(out, f"rank{rank}.pt"))

    tl.TrainLoop.run_loop = run_loop_and_dump

    def dump():
        with open(os.path.join(out, f"rank{rank}.json"), "w") as f:
            json.dump(record, f)

    atexit.register(dump)


def install_all() -> None:
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    install_clip_stub()
    install_bert_stub()
    install_smpl_stub()
    install_glove_stub()
    install_loader_workers()
    install_no_render()
    install_ddp_probe()


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        raise SystemExit(__doc__)
    install_all()
    if argv[0] == "-c":
        sys.argv = ["-c"] + argv[2:]
        exec(compile(argv[1], "<mdm_harness -c>", "exec"), {"__name__": "__main__"})
        return
    module = argv[0]
    sys.argv = [module] + argv[1:]
    import importlib
    mod = importlib.import_module(module)
    if hasattr(mod, "main") and module not in ("eval.eval_humanml",):
        mod.main()
    else:
        runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
