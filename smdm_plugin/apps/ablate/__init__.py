"""``smdm ablate``: A/B ablations of sparse keyframe mode on real motion, one results folder."""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Sequence, Set

import numpy as np
import torch

from ...io.files import OutputExistsError, atomic_write_json, atomic_write_text
from ..common.args import (add_common_flags, add_overwrite, existing_path, int_range, note_printer, output_path,
                           progress_of, resolve_device)
from ..common.provenance import make_provenance
from .grid import SHARED_SETTINGS, config_path, load_config, select_variants, slug, sparse_config
from .report import write_report
from .results import (MANIFEST, check_out_dir, FAILED_FILE, RESULT_FILE, Action, CacheState, Cached, Planned, Record, Status,  # noqa: F401
                      failure_record, is_ok, read_cached, row_from_cache)                                # (re-exported)

if TYPE_CHECKING:
    from ...training.data import MotionData

class StaleResultsError(OutputExistsError):
    """``--resume`` met results from another run (other settings, data, version, steps, seed or
    device) that it would have to replace."""


# ----------------------------------------------------------------------------------------- run
def run_variant(cfg: Dict[str, Any], variant: Dict[str, Any], data: "MotionData", device: torch.device,
                progress: bool = False, dist=None, checkpoint_dir: Optional[str] = None) -> Dict[str, Any]:
    """Train one variant with the in-package :class:`~smdm_plugin.training.trainer.Trainer` (DDP when
    ``dist`` is a torchrun context) and, on rank 0, evaluate it: validation loss, unconditional
    samples (EES, jitter, foot skating), keyframe error. Other ranks return after training.

    ``checkpoint_dir`` (one process only): the trainer's checkpoint is saved there every tenth of
    the steps and, when one is there, training continues from it (``smdm train --resume``'s
    mechanism: weights, optimiser, random streams, step), so an interrupted variant resumes
    bit-identically instead of starting over."""
    from ...runtime.distributed import DistContext
    from ...metrics.feature_measures import feature_quality, keyframe_interpolation_error_mm
    from ...training.trainer import TrainConfig, Trainer, resume
    from ...training.validation import validation_loss

    seed = int(cfg["seed"])
    sc = sparse_config(cfg, variant)
    steps = int(cfg["steps"])
    tc = TrainConfig(steps=steps, batch=int(cfg["batch"]), lr=float(cfg["lr"]),
                     diffusion_steps=int(cfg["diffusion_steps"]), seed=seed, model=dict(cfg["model"]), sparse=sc)
    trainer = Trainer(tc, data.train, dist=dist or DistContext(device=device))
    device = trainer.dist.device
    callback = None
    if checkpoint_dir is not None and trainer.dist.world_size == 1:
        resume(trainer, checkpoint_dir)  # nothing there: from step 0
        every = max(1, steps // 10)

        def callback(tr: Trainer, loss: float) -> None:
            if tr.step_count % every == 0 and tr.step_count < steps:
                tr.save(checkpoint_dir)

    try:
        result = trainer.train(progress=progress, callback=callback)
    except FloatingPointError as e:
        raise FloatingPointError(str(e).replace("Trainer: the ", "")) from None
    # losses of the whole run (a resumed one included); speed: the steps this call made
    model, diffusion, losses, train_s = trainer.model, trainer.diffusion, list(trainer.losses), result.seconds
    if not trainer.dist.is_main:
        return {"name": variant["name"], "status": Status.OK, "steps": steps, "rank": trainer.dist.rank}
    N = data.train.max_frames

    # evaluation: sample unconditionally (the variant's own sampling schedule), EES
    ev = cfg["eval"]
    ns, nf = int(ev.get("samples", 8)), min(int(ev.get("frames", 120)), N)
    model.eval()
    val_loss = validation_loss(model, diffusion, data.val, device, seed)
    g = torch.Generator().manual_seed(seed + 3)
    lengths = torch.full((ns,), nf, dtype=torch.long)
    y = {"mask": torch.ones(ns, 1, 1, nf, dtype=torch.bool, device=device), "lengths": lengths.to(device)}
    t1 = time.perf_counter()
    sample = diffusion.p_sample_loop(model, (ns, 263, 1, nf), {"y": y}, device=device, generator=g)
    sample_s = time.perf_counter() - t1
    motion = sample.squeeze(2).permute(0, 2, 1).cpu()  # [B, N, 263] normalised
    quality = feature_quality(motion, lengths, data.mean, data.std)
    val, val_lengths = data.val.padded()
    k = max(1, len(losses) // 10)
    smooth = np.convolve(losses, np.ones(k) / k, mode="valid") if losses else np.array([np.nan])
    return {
        "name": variant["name"], "status": Status.OK, "steps": steps,
        "final_loss": float(np.mean(losses[-k:])), "best_loss": float(np.min(smooth)), "val_loss": val_loss,
        "steps_per_s": result.steps / train_s if train_s > 0 else float("nan"), "train_s": train_s,
        "sample_s": sample_s, "resumed_at": steps - result.steps,
        "keyframe_error_mm": keyframe_interpolation_error_mm(val, val_lengths, data.val.joints, data.mean, data.std,
                                                             sc, ev.get("keyframe_motions"), seed),
        **quality, "losses": losses, "world_size": trainer.dist.world_size,
        "max_divergence": result.max_divergence,
        "sparse_config": None if sc is None else sc.to_dict(),
    }


# ----------------------------------------------------------------------------------------- results folder
def variant_settings(cfg: Dict[str, Any], variant: Dict[str, Any]) -> Dict[str, Any]:
    """Everything but the data that shapes a variant's result: the grid's shared settings, the
    variant entry and its resolved ``SparseConfig`` (``"invalid: ..."`` when it does not validate).
    Written to ``<slug>/config.json``; its hash is the provenance's ``config_hash``."""
    try:
        sc = sparse_config(cfg, variant)
        resolved: Any = None if sc is None else sc.to_dict()
    except (TypeError, ValueError) as e:
        resolved = f"invalid: {e}"
    return {**{k: cfg[k] for k in SHARED_SETTINGS}, "variant": variant, "sparse_config": resolved}


def variant_provenance(cfg: Dict[str, Any], variant: Dict[str, Any], data: MotionData,
                       device: torch.device) -> Dict[str, Any]:
    return make_provenance(variant_settings(cfg, variant), data.fingerprint, cfg["steps"], cfg["seed"], device.type,
                           data_root=os.path.abspath(str(data.root)), data_files=len(data.files))


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


CHECKPOINT_DIR = "checkpoint"


def _read_json_or_none(path: str) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def run_one(cfg: Dict[str, Any], variant: Dict[str, Any], data: "MotionData", dev: torch.device, vdir: str,
            provenance: Dict[str, Any], progress: bool, log: Callable[[str], Any], dist=None,
            resume: bool = False) -> Dict[str, Any]:
    """Run one variant and record it (atomically): ``result.json`` (its stale ``failed.json``
    removed) or, when it raises, ``failed.json`` (a previous ``result.json`` removed)."""
    name = variant["name"]
    res_path, fail_path = os.path.join(vdir, RESULT_FILE), os.path.join(vdir, FAILED_FILE)
    os.makedirs(vdir, exist_ok=True)
    atomic_write_json(os.path.join(vdir, "config.json"), variant_settings(cfg, variant))
    # an interrupted variant's checkpoint (smdm train's mechanism), used only by the same provenance
    ckpt = os.path.join(vdir, CHECKPOINT_DIR)
    ckpt_prov = os.path.join(ckpt, "provenance.json")
    if os.path.isdir(ckpt) and (not resume or _read_json_or_none(ckpt_prov) != json.loads(json.dumps(provenance))):
        shutil.rmtree(ckpt)
    os.makedirs(ckpt, exist_ok=True)
    atomic_write_json(ckpt_prov, provenance)
    t0 = time.perf_counter()
    try:
        res = run_variant(cfg, variant, data, dev, progress, dist, checkpoint_dir=ckpt)
    except Exception as e:  # recorded, the other variants go on
        rec = failure_record(name, e, provenance, wall_s=time.perf_counter() - t0)
        atomic_write_json(fail_path, rec)
        _remove(res_path)
        log(f"  {name}: FAILED ({rec['error']}); see {fail_path}")
        return rec
    res["wall_s"] = time.perf_counter() - t0
    res["provenance"] = provenance
    atomic_write_json(res_path, res, indent=None)
    _remove(fail_path)
    shutil.rmtree(ckpt, ignore_errors=True)  # the result is recorded: the checkpoint has done its job
    log(f"  {name}: loss {res['final_loss']:.4f}, {res['steps_per_s']:.2f} steps/s, {res['wall_s']:.0f} s")
    return res


def run_ablation(cfg: Dict[str, Any], out: str, data_root: str, device: str = "auto",
                 only: Optional[Sequence[str]] = None, progress: bool = True, log: Callable[[str], Any] = print,
                 resume: bool = False, overwrite: bool = False, dist=None) -> List[Dict[str, Any]]:
    """Run the grid ``cfg`` into ``out``; returns one row per variant of the grid, in its order.

    ``dist``: a torchrun context (:func:`~smdm_plugin.runtime.distributed.init_distributed`):
    every rank trains each variant with DDP; rank 0 alone decides what to run, evaluates, writes
    and logs (the other ranks return ``[]``).

    ``only``: the variants to run (names or folder names), the others keep their rows. An existing
    non-empty ``out`` needs ``resume`` (reuse current results, run the missing / failed /
    unreadable ones; results from another run stop it with :class:`StaleResultsError` before
    anything trains) or ``overwrite`` (run every selected variant again). See the module docstring.
    """
    from ...runtime.distributed import DistContext

    if resume and overwrite:
        raise ValueError("run_ablation: resume and overwrite exclude each other")
    ctx = dist or DistContext(device=resolve_device(device))
    main_rank = ctx.is_main
    if not main_rank:
        log = _quiet
    selected = select_variants(cfg, only)
    from ...io.outdir import OutputLock, check_no_overlap

    _on_main(ctx, lambda: (check_no_overlap(out, {"--data": data_root}), check_out_dir(out, resume, overwrite)))
    # one writer: rank 0 locks --out for the whole run (the other ranks never write)
    lock = OutputLock(out, "smdm ablate")
    _on_main(ctx, lambda: bool(lock.acquire()))  # only rank 0's object holds it
    try:
        return _run_locked(cfg, out, data_root, ctx, selected, progress, log, resume, overwrite)
    finally:
        lock.release()


def _run_locked(cfg: Dict[str, Any], out: str, data_root: str, ctx, selected: Set[str], progress: bool,
                log: Callable[[str], Any], resume: bool, overwrite: bool) -> List[Dict[str, Any]]:
    """:func:`run_ablation` once ``out`` is checked and locked."""
    import yaml

    main_rank = ctx.is_main
    dev = ctx.device
    from ...metrics.feature_measures import feature_quality
    from ...training.data import MotionData  # noqa: F811 - at run time

    data = MotionData(data_root, int(cfg["max_frames"]))
    log(f"ablate: {len(data.train)} training / {len(data.val)} validation motions from "
        f"{data_root} (fingerprint {data.fingerprint}); {cfg['steps']} steps x batch {cfg['batch']} per variant "
        f"on {dev}" + (f", {ctx.world_size} processes (DDP; batch per process)" if ctx.distributed else ""))

    def make_plan() -> List[Planned]:
        plan, conflicts = [], []
        for variant in cfg["variants"]:
            name = variant["name"]
            vdir = os.path.join(out, slug(name))
            prov = variant_provenance(cfg, variant, data, dev)
            cached = read_cached(vdir, prov)
            if name not in selected:
                action = Action.KEEP
            elif overwrite or cached.state in (CacheState.MISSING, CacheState.FAILED, CacheState.CORRUPT):
                action = Action.RUN
            elif cached.state is CacheState.CURRENT:
                action = Action.KEEP
            else:
                conflicts.append(f"{name!r} ({cached.reason})")
                action = Action.CONFLICT
            invalid = prov["settings"]["sparse_config"]
            if action is Action.RUN and isinstance(invalid, str):
                log(f"  {name}: {invalid} -- it will be reported as failed")
            plan.append(Planned(variant, vdir, prov, cached, action))
        if conflicts:
            raise StaleResultsError(
                f"--out {out!r} holds {len(conflicts)} result(s) from another run: {'; '.join(conflicts)}. Pass "
                "--overwrite to run them again (replacing them), leave them out with --only, or pick another --out")
        return plan

    plan = _on_main(ctx, make_plan)  # rank 0 reads the folder; every rank follows its plan
    if not main_rank:
        for item in plan:
            if item.action is Action.RUN:
                try:
                    run_variant(cfg, item.variant, data, dev, False, ctx)
                except Exception:  # rank 0 fails alike and records it
                    pass
        return []

    os.makedirs(out, exist_ok=True)
    from ... import __version__

    atomic_write_json(os.path.join(out, MANIFEST), {
        "tool": "smdm ablate", "format": 1, "grid": cfg.get("name"), "variants": [v["name"] for v in cfg["variants"]],
        "package_version": __version__, "data_root": os.path.abspath(data_root), "data_fingerprint": data.fingerprint,
        "device": dev.type, "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    atomic_write_text(os.path.join(out, "config.yaml"), yaml.safe_dump(cfg, sort_keys=False))
    real = feature_quality(*data.val.padded(), data.mean, data.std)
    rows = [row_from_cache(item.variant["name"], item.cached) for item in plan]
    try:
        for k, item in enumerate(plan):
            name, cached = item.variant["name"], item.cached
            if item.action is not Action.RUN:
                if name in selected:
                    log(f"  {name}: reused (same provenance; {os.path.join(item.vdir, RESULT_FILE)})")
                continue
            if cached.state in (CacheState.CORRUPT, CacheState.STALE):
                log(f"  {name}: replacing {cached.state} result ({cached.reason})")
            rows[k] = run_one(cfg, item.variant, data, dev, item.vdir, item.provenance, progress, log, ctx,
                              resume=resume)
    finally:  # the report is written even when interrupted (Ctrl-C): it then shows what is done
        write_report(rows, out, real["ees"], cfg, data.fingerprint, real=real)
    return rows


def _quiet(*_: Any, **__: Any) -> None:
    """The log of ranks > 0: nothing."""


def _on_main(ctx, fn: Callable[[], Any]) -> Any:
    """``fn()`` run on rank 0 only; its result, or the exception it raised, is handed to every rank
    (so all ranks follow one decision, or all stop with the same error)."""
    if not ctx.distributed:
        return fn()
    box: List[Any] = [None]
    if ctx.is_main:
        try:
            box[0] = ("ok", fn())
        except Exception as e:  # noqa: BLE001 - re-raised on every rank
            box[0] = ("error", e)
    torch.distributed.broadcast_object_list(box, src=0)
    kind, value = box[0]
    if kind == "error":
        raise value
    return value


# ----------------------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="smdm ablate", description=__doc__.split("\n\n")[0],
        epilog="An existing non-empty --out needs --resume (reuse results with the same provenance, run the rest) "
               "or --overwrite (run the selected variants again). Exit status: 0 all selected variants ok, "
               "1 one failed, 2 bad arguments or a refused --out, 130 interrupted.")
    p.add_argument("--config", default="table1",
                   help="the grid: a YAML path or a packaged grid name (table1, defaults, quick; quality_compute runs "
                        "the quality-versus-compute study)")
    p.add_argument("--out", default=os.path.join("results", "ablate"), type=output_path(),
                   help="results folder (default results/ablate)")
    p.add_argument("--data", type=existing_path("dir"), default=None,
                   help="HumanML3D-format folder: new_joint_vecs/, Mean.npy, Std.npy, train.txt, val.txt or "
                        "test.txt (default: the grid's 'data'; required when the grid has none)")
    p.add_argument("--steps", type=int_range(1), default=None, help="override the config's steps per variant (>= 1)")
    p.add_argument("--only", nargs="+", default=None, metavar="VARIANT",
                   help="run only these variants (names or folder names); the other rows are kept")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true",
                   help="continue in an existing --out: reuse results with the same provenance, run the rest")
    add_overwrite(g)
    add_common_flags(p)
    p.add_argument("--quick", action="store_true",
                   help="the quick (seconds) variant of a study config (quality_compute): see smdm_plugin.apps.ablate.study")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    from . import study

    if study.wants_study(argv):  # kind: quality_compute (or --quick): the quality-versus-compute study
        return study.main(argv, list(build_parser()._option_string_actions))
    p = build_parser()
    a = p.parse_args(argv)
    try:
        cfg = load_config(a.config)
        from ...io.outdir import check_no_overlap

        check_no_overlap(a.out, {"--config": config_path(a.config)})  # the grid is an input too
    except (FileNotFoundError, ValueError, OutputExistsError) as e:
        p.error(str(e))
    if a.steps is not None:
        cfg["steps"] = a.steps
    try:
        selected = select_variants(cfg, a.only)
    except ValueError as e:
        p.error(f"argument --only: {e}")
    from ..common.threads import apply_threads
    apply_threads(a.threads)
    data_root = a.data or cfg.get("data")
    if not data_root:
        p.error("argument --data: give a HumanML3D-format folder (new_joint_vecs/, Mean.npy, Std.npy, train.txt, "
                "val.txt or test.txt), e.g. HumanML3D itself; the embedded CMU clips are joint positions, not "
                "263-D features: `smdm demo` compares dense and sparse on them")
    cfg["data"] = data_root
    from ...runtime.distributed import init_distributed, shutdown_distributed

    try:
        ctx = init_distributed(a.device)  # under torchrun: join the group (gloo on CPU, nccl on CUDA)
    except ValueError as e:
        print(f"smdm ablate: error: {e}", file=sys.stderr)
        return 2
    try:
        results = run_ablation(cfg, a.out, data_root, a.device, a.only, progress=ctx.is_main and progress_of(a),
                               log=note_printer(a), resume=a.resume, overwrite=a.overwrite, dist=ctx)
    except (OutputExistsError, FileNotFoundError, ValueError, PermissionError, NotADirectoryError) as e:
        if ctx.is_main:
            print(f"smdm ablate: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nsmdm ablate: interrupted; finished variants are kept in {a.out} (results.md shows them). "
              "Rerun with --resume to continue.", file=sys.stderr)
        return 130
    finally:
        shutdown_distributed(ctx)
    if not ctx.is_main:
        return 0
    with open(os.path.join(a.out, "results.md")) as f:
        print("\n" + f.read())
    note_printer(a)(f"results: {os.path.abspath(a.out)}")
    return 0 if all(is_ok(r) for r in results if r["name"] in selected) else 1

if __name__ == "__main__":
    sys.exit(main())
