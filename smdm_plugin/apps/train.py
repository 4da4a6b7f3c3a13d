"""``smdm train``: train the in-package TinyMDM (dense or ``--sparse``) on a HumanML3D-format
folder and save a checkpoint folder (``training/trainer.py``); under ``torchrun``: DDP, only rank 0
writes."""
from __future__ import annotations

import argparse
import json
import os
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..core.config import SparseConfig
from ..support.config_files import CONFIG_FILENAME
from ..runtime.compile import COMPILE_MODES, default_backend
from ..runtime.distributed import init_distributed
from ..io.checkpoint_files import BACKBONE_FILENAME
from ..io.files import (atomic_open, atomic_write_json, atomic_write_text, describe_changes, digests_fingerprint,
                        file_digests)
from ..io.humanml3d import load_humanml3d
from ..reference.text import TextConfig
from ..training.data import MotionSet, check_clip_lengths
from ..training.trainer import (DEFAULT_MODEL, TRAIN_CONFIG_FILENAME, TRAIN_STATE_FILENAME, TrainConfig, Trainer,
                                TrainResult, resume)
from .common.args import (add_common_flags, add_overwrite, compile_backend, float_range, int_range, note_printer,
                          output_path, progress_of, seed_type)
from .common.threads import apply_threads


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="smdm train",
        description="Train the in-package TinyMDM (dense, or sparse keyframe mode with --sparse) on a "
                    "HumanML3D-format folder and save a checkpoint folder that smdm_plugin.load_checkpoint "
                    "reloads. Under torchrun (torchrun --nproc_per_node N -m smdm_plugin train ...) it trains "
                    "with DistributedDataParallel; --batch is per process.",
        epilog="example: torchrun --nproc_per_node 2 -m smdm_plugin train --data dataset/HumanML3D "
               "--out runs/smdm --sparse")
    p.add_argument("--data", required=True, metavar="DIR",
                   help="HumanML3D-format folder (new_joint_vecs/, Mean.npy, Std.npy, <split>.txt)")
    p.add_argument("--split", default="train", help="which <split>.txt to train on (default: train)")
    p.add_argument("--max-frames", type=int_range(2, 10000), default=196,
                   help="frames per sample; longer motions are cut (default: 196)")
    p.add_argument("--min-frames", type=int_range(2, 10000), default=40,
                   help="skip shorter motions (default: 40)")
    p.add_argument("--out", required=True, metavar="DIR", type=output_path(),
                   help="checkpoint folder to write; each checkpoint appears there as it is made")
    add_overwrite(p)
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out (interrupted, or finished and given more --steps) from its last "
                        "checkpoint: weights, optimiser, random streams and step count, as if never stopped; "
                        "the data must have the same content (a copy elsewhere is fine)")
    p.add_argument("--init-from", metavar="PATH", default=None,
                   help="start from a DENSE checkpoint (an smdm train --out folder of the same model options, or its "
                        "model*.pt): its weights are loaded; with --sparse the recipe's new layers are fitted to the "
                        "dense ones (warm start, errors printed); fresh optimiser; train_config.json records the "
                        "origin (path + sha256)")
    p.add_argument("--init-amplitude", type=float_range(0.0, 3.0, lo_open=True), default=0.05, metavar="RAD",
                   help="with --init-from --sparse: largest pre-activation (radians) of the fitted sine layers; small "
                        "= closer to the dense layer, larger = larger first-layer weights, which Adam's fixed step "
                        "moves relatively less (default 0.05)")
    t = p.add_argument_group("training")
    t.add_argument("--steps", type=int_range(1), default=1000, help="optimiser steps (default: 1000)")
    t.add_argument("--batch", type=int_range(1), default=16,
                   help="samples per process and step; global batch = batch x processes (default: 16)")
    t.add_argument("--lr", type=float_range(0.0, lo_open=True), default=2e-4, help="AdamW learning rate (default 2e-4)")
    t.add_argument("--weight-decay", type=float_range(0.0), default=0.0, help="AdamW weight decay (default 0)")
    t.add_argument("--grad-clip", type=float_range(0.0), default=0.0, help="max gradient norm (default 0: off)")
    t.add_argument("--diffusion-steps", type=int_range(1, 100000), default=100, help="diffusion steps T (default 100)")
    t.add_argument("--seed", type=seed_type, default=0, help="random seed (default 0)")
    t.add_argument("--save-every", type=int_range(0), default=0,
                   help="also save a checkpoint every this many steps (default 0: only at the end)")
    t.add_argument("--compile", nargs="?", const="default", default="none", choices=COMPILE_MODES, metavar="MODE",
                   help="capture the whole training step (loss forward and backward; AdamW fused on CUDA; under "
                        "torchrun the model call, inside DDP), dense or sparse: none (default), default (also the "
                        "bare --compile) or reduce-overhead (CUDA graphs; CUDA only, else default with a warning); "
                        "docs/compile.md")
    t.add_argument("--compile-backend", type=compile_backend, default=None,
                   help="torch.compile backend (default: $SMDM_COMPILE_BACKEND when set, else inductor; the same "
                        "knob as upstream scripts' --sparse_compile backend)")
    m = p.add_argument_group("model (TinyMDM)")
    m.add_argument("--arch", choices=("trans_enc", "trans_dec"), default=DEFAULT_MODEL["arch"],
                   help=f"MDM architecture (default {DEFAULT_MODEL['arch']})")
    m.add_argument("--latent-dim", type=int_range(8, 65536), default=DEFAULT_MODEL["latent_dim"],
                   help=f"transformer width (default {DEFAULT_MODEL['latent_dim']}; MDM: 512)")
    m.add_argument("--layers", type=int_range(1, 256), default=DEFAULT_MODEL["num_layers"],
                   help=f"transformer layers (default {DEFAULT_MODEL['num_layers']}; MDM: 8)")
    m.add_argument("--heads", type=int_range(1, 256), default=DEFAULT_MODEL["num_heads"],
                   help=f"attention heads (default {DEFAULT_MODEL['num_heads']})")
    m.add_argument("--ff-size", type=int_range(1, 1 << 20), default=DEFAULT_MODEL["ff_size"],
                   help=f"feed-forward width (default {DEFAULT_MODEL['ff_size']}; MDM: 1024)")
    m.add_argument("--dropout", type=float_range(0.0, 1.0, hi_open=True), default=DEFAULT_MODEL["dropout"],
                   help=f"dropout probability (default {DEFAULT_MODEL['dropout']})")
    c = p.add_argument_group("text conditioning (off by default: unconditional)")
    c.add_argument("--text", action="store_true",
                   help="train text-conditioned on texts/<id>.txt with the frozen hashed bag-of-words encoder "
                        "(reference/text.py; saved as text_encoder.json) and classifier-free-guidance dropout")
    c.add_argument("--cond-mask-prob", type=float_range(0.0, 1.0, hi_open=True), default=0.1,
                   help="with --text: fraction of samples trained without their caption (default 0.1, as MDM)")
    c.add_argument("--guidance-scale", type=float_range(0.0), default=2.5,
                   help="with --text: classifier-free guidance scale saved for sampling (default 2.5, as MDM)")
    SparseConfig.add_argparse_args(p, "sparse keyframe mode (sMDM)")
    for action in p._actions:  # set by the trainer itself, or meaningless for an unconditional TinyMDM
        if action.dest in _NOT_CLI_SPARSE:
            action.help = argparse.SUPPRESS
    r = p.add_argument_group("run")
    add_common_flags(r, device_help="auto (cuda:LOCAL_RANK when CUDA is available), cpu, cuda, cuda:N, mps")
    return p


_NOT_CLI_SPARSE = {"sparse_diffusion_steps": "set from --diffusion-steps",
                   "sparse_prefix_frames": "TinyMDM has no DiP prefix here",
                   "sparse_text_encoder": "TinyMDM is trained unconditionally here"}


def _parse(argv: Optional[List[str]]) -> Tuple[Any, TrainConfig]:
    p = build_parser()
    a = p.parse_args(argv)
    if a.resume and a.overwrite:
        p.error("argument --overwrite: not allowed with argument --resume")
    if a.resume and a.init_from:
        p.error("argument --init-from: not allowed with argument --resume (the run's weights come from its checkpoint)")
    if a.min_frames > a.max_frames:
        p.error(f"--min-frames ({a.min_frames}) must be <= --max-frames ({a.max_frames})")
    if a.latent_dim % a.heads:
        p.error(f"--latent-dim ({a.latent_dim}) must be a multiple of --heads ({a.heads})")
    for dest in ("cond_mask_prob", "guidance_scale"):
        if not a.text and getattr(a, dest) != p.get_default(dest):
            p.error(f"--{dest.replace('_', '-')}: applies only with --text (text-conditioned training)")
    for dest in _NOT_CLI_SPARSE:
        if getattr(a, dest) != p.get_default(dest):
            p.error(f"--{dest}: not an option of smdm train ({_NOT_CLI_SPARSE[dest]})")
    if not a.sparse:   # a setting that cannot apply to a dense run is an error, never dropped silently
        for dest in sorted(vars(a)):
            if dest.startswith("sparse_") and getattr(a, dest) != p.get_default(dest):
                p.error(f"--{dest}: applies only with --sparse (this run is dense)")
    if a.init_amplitude != p.get_default("init_amplitude") and not (a.sparse and a.init_from):
        p.error("--init-amplitude: applies only with --init-from and --sparse (the fitted sine layers)")
    try:
        sparse = SparseConfig.from_args(a) if a.sparse else None
    except ValueError as e:
        p.error(str(e))
    model = {"latent_dim": a.latent_dim, "num_layers": a.layers, "num_heads": a.heads, "ff_size": a.ff_size,
             "arch": a.arch, "dropout": a.dropout}
    cfg = TrainConfig(steps=a.steps, batch=a.batch, lr=a.lr, weight_decay=a.weight_decay, grad_clip=a.grad_clip,
                      diffusion_steps=a.diffusion_steps, seed=a.seed, model=model, sparse=sparse,
                      compile=a.compile, compile_backend=a.compile_backend or default_backend(),
                      text=TextConfig(cond_mask_prob=a.cond_mask_prob, guidance_scale=a.guidance_scale) if a.text else None)
    return a, cfg


#: what ``smdm train`` writes besides ``model<step>.pt``
OUTPUT_FILES = (BACKBONE_FILENAME, CONFIG_FILENAME, TRAIN_CONFIG_FILENAME, TRAIN_STATE_FILENAME, "Mean.npy",
                "Std.npy", "losses.csv", "loss.png", "result.json", "motion.json",
                "text_encoder.json", "data_files.json")
#: a checkpoint's weights, ``model<step>.pt``
CHECKPOINT_PATTERN = "model[0-9][0-9][0-9][0-9][0-9][0-9][0-9][0-9][0-9].pt"
#: the names ``smdm train`` writes (an ``--overwrite`` refuses such a file it did not write itself)
OUTPUT_PATTERNS = OUTPUT_FILES + (CHECKPOINT_PATTERN,)
#: what makes ``--out`` a run to protect: a checkpoint (a run that failed before one is started over)
PROTECTED = (CHECKPOINT_PATTERN, TRAIN_STATE_FILENAME)


def write_logs(folder: str, losses: Sequence[float], result: Optional[TrainResult] = None,
               compile_setting: Optional[Dict[str, Any]] = None) -> None:
    """``losses.csv`` (step, loss), ``loss.png`` and, with ``result``, ``result.json`` (with
    ``compile_setting``: how the model ran, under ``compile``)."""
    lines = ["step,loss"] + [f"{i + 1},{v:.9g}" for i, v in enumerate(losses)]
    atomic_write_text(os.path.join(folder, "losses.csv"), "\n".join(lines) + "\n")
    if result is not None:
        d = result.to_dict()
        if compile_setting is not None:
            d["compile"] = compile_setting
        atomic_write_json(os.path.join(folder, "result.json"), d)
    if losses:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4))
        k = max(1, len(losses) // 50)
        smooth = np.convolve(losses, np.ones(k) / k, mode="valid")
        ax.plot(np.arange(1, len(losses) + 1), losses, lw=0.5, alpha=0.4, label="per step")
        ax.plot(np.arange(k, len(losses) + 1), smooth, lw=1.5, label=f"moving average ({k})")
        ax.set_xlabel("optimiser step")
        ax.set_ylabel("training loss")
        ax.set_yscale("log")
        ax.legend()
        fig.tight_layout()
        with atomic_open(os.path.join(folder, "loss.png"), "wb") as f:
            fig.savefig(f, format="png", dpi=110)
        plt.close(fig)


def main(argv: Optional[List[str]] = None) -> int:
    """``smdm train``; returns the exit status (2: bad arguments, data or output folder)."""
    import sys
    from contextlib import ExitStack

    from ..runtime.distributed import shutdown_distributed
    from ..io.files import OutputExistsError
    from ..io.outdir import OutputDir
    from ..training.memory import check_batch_fits
    from .common.signals import check as stop_check

    a, cfg = _parse(argv)
    say = note_printer(a)
    apply_threads(a.threads)
    try:
        split = load_humanml3d(a.data, a.split, a.max_frames, a.min_frames, captions=a.text)
        data = MotionSet.from_split(split, captions=a.text)
        if cfg.sparse is not None:
            check_clip_lengths(data, cfg.sparse, a.data)
        ctx = init_distributed(a.device)
    except (FileNotFoundError, ValueError) as e:
        print(f"smdm train: {e}", file=sys.stderr)
        return 2
    try:
        try:  # a batch that cannot fit is refused before anything is written
            check_batch_fits(cfg.batch, data.max_frames, data.feature_dim, cfg.model, cfg.sparse, ctx.device,
                             int(os.environ.get("LOCAL_WORLD_SIZE", "1")) if ctx.device.type == "cpu" else 1)
        except ValueError as e:
            if ctx.is_main:
                print(f"smdm train: error: {e}", file=sys.stderr)
            return 2
        with ExitStack() as stack:
            message, od = "", None
            if ctx.is_main:
                od = OutputDir(a.out, overwrite=a.overwrite, inputs={"--data": a.data, "--init-from": a.init_from},
                               command="smdm train", owns=OUTPUT_PATTERNS, resumable=True, resume=a.resume,
                               protects=PROTECTED)
                try:
                    stack.enter_context(od)
                    if a.resume and od.resumed_from is None:
                        od.abandon(keep=False)  # nothing written: leave no folder behind
                        raise OutputExistsError(f"--resume: {a.out!r} holds no run to continue (no interrupted or "
                                                "finished smdm train run there)")
                except (OutputExistsError, OSError) as e:
                    from ..io.outdir import describe_os_error

                    message = str(e) if isinstance(e, OutputExistsError) else describe_os_error(e)
            if not ctx.broadcast_flag(not message):
                if ctx.is_main:
                    print(f"smdm train: {message}", file=sys.stderr)
                return 2
            # written in --out itself (OutputDir live): each checkpoint visible as it is made
            folder = od.path if od is not None else os.path.abspath(a.out)  # other ranks only read it (--resume)
            try:
                trainer = Trainer(cfg, data, dist=ctx, init_from=a.init_from, init_amplitude=a.init_amplitude)
            except (FileNotFoundError, ValueError) as e:
                if od is not None:
                    print(f"smdm train: {e}", file=sys.stderr)
                    od.abandon(keep=False)
                return 2
            digests = file_digests(a.data, split.files)  # the data by content: a copy elsewhere is the same data
            extra = {"data": os.path.abspath(a.data), "split": a.split, "min_frames": a.min_frames,
                     "max_frames": a.max_frames, "data_fingerprint": digests_fingerprint(digests)}
            note = ""
            if a.resume:
                try:
                    note = "; " + resume(trainer, folder)
                    if os.path.exists(os.path.join(folder, TRAIN_STATE_FILENAME)):
                        check_same_data(folder, extra, digests, a.out)
                except ValueError as e:
                    if od is not None:
                        print(f"smdm train: {e}", file=sys.stderr)
                        od.abandon(keep=od.resumed_from == od.path)  # an interrupted run's folder stays as it was
                    return 2
            extra["compile_applied"] = trainer.compile_setting.to_dict()  # after --resume's data check
            if ctx.is_main:
                kind = "sparse" if cfg.sparse is not None else "dense"
                say(f"smdm train: {kind} TinyMDM, {len(data)} motions from {a.data} ({a.split}), {cfg.steps} steps "
                      f"x global batch {trainer.global_batch} ({ctx.world_size} process(es) x {cfg.batch}) on "
                      f"{ctx.device}" + (f", backend {torch.distributed.get_backend()}" if ctx.distributed else "")
                      + f", {trainer.compile_setting.describe()}" + note, flush=True)
                if trainer.init_origin is not None:
                    say(f"smdm train: initialised from the dense checkpoint {trainer.init_origin['path']} "
                          f"({trainer.init_origin['digest'][:19]}...)"
                          + (f"; {trainer.init_origin['fit_summary']}" if "fit_summary" in trainer.init_origin else ""),
                          flush=True)

            if ctx.is_main:
                write_data_digests(folder, digests)

            def every(tr: Trainer, loss: float) -> None:
                stop_check()  # a Ctrl-C / SIGTERM the compiler swallowed stops here
                if a.save_every and tr.step_count % a.save_every == 0 and tr.step_count < cfg.steps:
                    tr.save(folder, extra)
                    if ctx.is_main:
                        write_logs(folder, tr.losses)

            try:
                result = trainer.train(progress=progress_of(a), callback=every)
            except KeyboardInterrupt:
                if ctx.is_main:
                    done = (trainer.step_count // a.save_every) * a.save_every if a.save_every else 0
                    print(f"\nsmdm train: interrupted at step {trainer.step_count}; " + (
                        f"rerun with --resume to continue from step {done}" if done else
                        "no checkpoint was saved (--save-every N saves one every N steps)"), file=sys.stderr)
                raise
            trainer.save(folder, extra)
            if ctx.is_main:
                write_logs(folder, trainer.losses, result, trainer.compile_setting.to_dict())
            ctx.barrier()
        if ctx.is_main:
            path = os.path.join(a.out, trainer.checkpoint_name())
            print(f"smdm train: {result.steps} steps in {result.seconds:.1f} s ({result.steps_per_s:.2f} steps/s, "
                  f"{result.samples_per_s:.1f} samples/s), final loss {result.final_loss:.4f}; ranks in sync: "
                  f"max |difference| {result.max_divergence:.3g}")
            say(f"saved {path}")
        return 0
    finally:
        shutdown_distributed(ctx)


#: per-file content digests of the training data (``--resume`` names the files that changed)
DATA_DIGESTS_FILENAME = "data_files.json"


def write_data_digests(folder: str, digests: Dict[str, str]) -> None:
    """``data_files.json``: ``{"fingerprint", "files": {relative name: digest}}`` (atomic; kept when equal)."""
    path = os.path.join(folder, DATA_DIGESTS_FILENAME)
    doc = {"fingerprint": digests_fingerprint(digests), "files": digests}
    try:
        if _read_json(path) == doc:
            return
    except ValueError:
        pass
    atomic_write_json(path, doc)


def check_same_data(folder: str, extra: Dict[str, Any], digests: Dict[str, str], out: str) -> None:
    """``ValueError`` when the run in ``folder`` was trained on other data than ``extra`` describes:
    the data is identified by content (``data_fingerprint``), not by path, so an identical copy
    elsewhere continues the run and data changed in place is refused, naming the files that changed.
    Runs saved before the fingerprint existed are compared by path."""
    saved = _read_json(os.path.join(folder, TRAIN_CONFIG_FILENAME))
    keys = ["split", "min_frames", "max_frames"] + (["data_fingerprint"] if "data_fingerprint" in saved else ["data"])
    differ = [k for k in keys if saved.get(k) != extra[k]]
    if not differ:
        return
    what = "; ".join(f"{k}: saved {saved.get(k)!r}, now {extra[k]!r}" for k in differ if k != "data_fingerprint")
    if "data_fingerprint" in differ:
        try:
            old = _read_json(os.path.join(folder, DATA_DIGESTS_FILENAME))["files"]
            changes = describe_changes(old, digests) if isinstance(old, dict) else "contents differ"
        except (ValueError, KeyError):
            changes = "contents differ"
        what = "; ".join(w for w in (what, f"--data {extra['data']}: {changes}") if w)
    raise ValueError(f"--resume: {out} was trained on other data ({what}); resume with the same data, or start a "
                     "new run")


def _read_json(path: str) -> Dict[str, Any]:
    """A JSON object file (errors name it)."""
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read().decode("utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{path}: missing") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{path}: not valid UTF-8 JSON ({e})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


if __name__ == "__main__":
    import sys

    sys.exit(main())
