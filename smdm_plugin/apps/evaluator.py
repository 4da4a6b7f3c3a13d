"""``smdm evaluator train``: train a T2M-architecture evaluator on your own captioned motion and
report how far to trust it (held-out R-precision beside the weights); ``smdm evaluator check``:
measure what it can resolve (the sensitivity table, ``EDIR/sensitivity.json``).

    smdm evaluator train --data dataset/MyMotion --out evaluators/mine      # HumanML3D layout
    smdm evaluator train --out evaluators/cmu                               # the embedded CMU clips
    smdm evaluator check evaluators/mine --data dataset/MyMotion            # noise, smoothing, reversal, ...

The folder it writes (``evaluator.json``: config, vocabulary, held-out accuracy, history;
``evaluator.pt``; ``metrics.json``; ``train_state.pt`` for ``--resume``) is what ``smdm eval
--evaluator`` and :func:`smdm_plugin.load_evaluator` read.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any, Dict, List, Optional

STATE_FILENAME = "train_state.pt"
#: replications of the R-precision check at the end of training (smdm eval's default)
CHECK_REPLICATIONS = 20
OUTPUTS = ("evaluator.json", "evaluator.pt", "metrics.json", STATE_FILENAME)


from .common.args import note_printer, progress_of


def build_parser() -> argparse.ArgumentParser:
    from ..metrics.evaluator.train import DEFAULT_RECIPE, OWN_SIZES, RECIPES, SELECTIONS, T2M_SIZES, TrainSettings
    from .common.args import (add_common_flags, add_overwrite, existing_path, float_range, int_range, output_path,
                              seed_type)

    d = TrainSettings(recipe=DEFAULT_RECIPE)
    p = argparse.ArgumentParser(
        prog="smdm evaluator train",
        description="Train the T2M evaluator's architecture (movement conv encoder, motion and text BiGRUs) on the "
                    "train split of a HumanML3D-format folder (default: the CMU clips embedded in the package) with "
                    "T2M's recipe (movement auto-encoder, then a margin loss with the movement encoder frozen), and "
                    "write its held-out R-precision beside the weights.")
    p.add_argument("--data", type=existing_path("dir"), default=None, metavar="DIR",
                   help="HumanML3D-format folder: new_joint_vecs/, texts/ (caption#word/POS ...#from#to), Mean.npy, "
                        "Std.npy, train.txt (+ val.txt, test.txt for the held-out accuracy); default: the embedded "
                        "CMU clips (joints66 features, CMU's descriptions as captions)")
    p.add_argument("--out", required=True, metavar="EDIR", type=output_path(), help="evaluator folder to write")
    p.add_argument("--glove", type=existing_path("dir"), default=None, metavar="DIR",
                   help="T2M's GloVe folder (our_vab_data.npy, our_vab_words.pkl, our_vab_idx.pkl); default: word "
                        "embeddings learned from the training captions")
    p.add_argument("--recipe", choices=RECIPES, default=d.recipe,
                   help="t2m: T2M's two stages (movement auto-encoder, then the BiGRUs with a margin loss on shifted "
                        "negatives, movement encoder frozen) at T2M's sizes; contrastive: 0.4's one stage (batch "
                        f"cross-entropy, everything trained, small sizes) (default: {d.recipe})")
    p.add_argument("--epochs", type=int_range(1, 100000), default=None,
                   help=f"text-motion matching epochs (default: {d.epochs})")
    p.add_argument("--ae-epochs", type=int_range(0, 100000), default=d.ae_epochs,
                   help=f"t2m: movement auto-encoder epochs before matching (default: {d.ae_epochs})")
    p.add_argument("--margin", type=float_range(0.0, lo_open=True), default=d.margin,
                   help=f"t2m: distance negatives are pushed beyond (default: {d.margin}, T2M's)")
    p.add_argument("--select", choices=SELECTIONS, default=None,
                   help="how the kept matching epoch is chosen on the val split: val_loss (T2M's: the lowest "
                        "validation loss) or val_rprec (the highest validation R-precision) (default: val_loss for "
                        "t2m, val_rprec for contrastive)")
    p.add_argument("--reversed-negatives", action=argparse.BooleanOptionalAction, default=None,
                   help="t2m: push each caption away from its own motion played backwards, so that R-precision "
                        "sees the order of a motion (default: on for t2m; docs/evaluation.md)")
    p.add_argument("--batch", type=int_range(2, 4096), default=d.batch, help=f"motions per step (default: {d.batch})")
    p.add_argument("--lr", type=float_range(0.0, lo_open=True), default=None,
                   help=f"Adam, matching stage (default: {d.lr} for t2m, 1e-3 for contrastive)")
    p.add_argument("--seed", type=seed_type, default=d.seed,
                   help=f"seed of the initial weights, the batch order and the caption draws (default: {d.seed})")
    p.add_argument("--dim", type=int_range(4, 4096), default=None,
                   help=f"co-embedding size (default: {T2M_SIZES['dim_coemb']} for t2m, as upstream; "
                        f"{OWN_SIZES['dim_coemb']} for contrastive)")
    p.add_argument("--hidden", type=int_range(4, 8192), default=None,
                   help=f"hidden size of every encoder (default: the recipe's: t2m {T2M_SIZES['dim_movement_hidden']} "
                        f"and {T2M_SIZES['dim_motion_hidden']} for the motion BiGRU, as upstream; contrastive "
                        f"{OWN_SIZES['dim_motion_hidden']})")
    p.add_argument("--resume", action="store_true", help=f"continue from --out/{STATE_FILENAME} (to --epochs)")
    add_overwrite(p)
    add_common_flags(p)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print("usage: smdm evaluator train [options]   ('smdm evaluator train --help' for the options)",
              file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help"):
        top = argparse.ArgumentParser(prog="smdm evaluator", description="T2M-style text-motion evaluators")
        sub = top.add_subparsers(dest="command", metavar="{train,check}")
        sub.add_parser("train", parents=[build_parser()], add_help=False,
                       help="train an evaluator on a HumanML3D-format folder (or the embedded clips)")
        sub.add_parser("check", parents=[build_check_parser()], add_help=False,
                       help="measure what an evaluator resolves (noise, smoothing, reversal, foot sliding, caption "
                            "swap, the real-vs-real floor) and save the table beside it")
        top.parse_args(argv)      # prints the help and exits 0
    if argv[0] == "check":
        from .common.args import existing_path, positional_type

        p = build_check_parser()
        a = p.parse_args(argv[1:])
        positional_type(p, a, "evaluator", existing_path("dir"), "EDIR")
        return run_check(a, p)
    if argv[0] != "train":
        print(f"smdm evaluator: error: unknown subcommand {argv[0]!r} (expected: train, check)", file=sys.stderr)
        return 2
    p = build_parser()
    a = p.parse_args(argv[1:])
    return run(a, p)


def run(a: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    from ..io.files import OutputExistsError
    from ..io.outdir import OutputDir, open_or_refuse
    from ..metrics.evaluator.data import load_split, split_names
    from ..metrics.evaluator.train import build_evaluator

    from .common.threads import apply_threads

    if a.resume and a.overwrite:
        p.error("argument --overwrite: not allowed with argument --resume")
    apply_threads(a.threads)
    try:
        settings = settings_from_args(a)
    except ValueError as e:
        p.error(str(e))
    # as smdm train: locked, apart from the inputs, written into --out as it trains (each file atomic;
    # docs/reliability.md); --resume continues an interrupted or a finished run on the same data
    od = OutputDir(a.out, overwrite=a.overwrite, inputs={"--data": a.data, "--glove": a.glove},
                   command="smdm evaluator train", owns=OUTPUTS, resumable=True, resume=a.resume)
    try:
        od.check()  # refused before anything is loaded or written
    except OutputExistsError as e:
        print(f"smdm evaluator train: error: {e}", file=sys.stderr)
        return 2
    try:
        train = load_split(a.data, "train")
        held = {s: load_split(a.data, s) for s in split_names(a.data)}
    except (FileNotFoundError, ValueError) as e:
        print(f"smdm evaluator train: {e}", file=sys.stderr)
        return 2
    try:
        from .common.args import resolve_device

        ev = build_evaluator(train, settings, glove=a.glove).to(resolve_device(a.device))
    except (FileNotFoundError, ValueError) as e:
        print(f"smdm evaluator train: {e}", file=sys.stderr)
        return 2
    if not open_or_refuse(od, "smdm evaluator train"):
        return 2
    with od:
        if a.resume and od.resumed_from is None:
            od.abandon(keep=False)  # nothing written: leave no folder behind
            print(f"smdm evaluator train: error: --resume: {a.out!r} holds no run to continue (no interrupted or "
                  "finished smdm evaluator train run there)", file=sys.stderr)
            return 2
        status = _train(a, od, settings, ev, train, held)
    if status == 0:
        note_printer(a)(f"saved {os.path.abspath(a.out)}")
    return status


def _train(a: argparse.Namespace, od: Any, settings: Any, ev: Any, train: Any, held: Dict[str, Any]) -> int:
    """Train ``ev`` (with ``--resume``: from the state in ``od.path``) and write :data:`OUTPUTS` into
    ``od.path`` (``--out`` itself: each file written atomically as training goes; an :class:`~smdm_plugin.io.outdir.OutputDir`);
    a refused resume abandons ``od`` and returns 2."""
    import time

    import torch

    from ..io.checkpoint_files import read_state_dict
    from ..io.files import atomic_open, atomic_write_json
    from ..metrics.evaluator.model import save_evaluator
    from ..metrics.evaluator.check import retrieval_check
    from ..metrics.evaluator.train import held_out_accuracy, train_evaluator

    folder = od.path
    state_path = os.path.join(folder, STATE_FILENAME)
    digests = data_digests(train, held)
    state = None
    if a.resume:
        try:
            if not os.path.isfile(state_path):
                raise ValueError(f"--resume: no {STATE_FILENAME} in {a.out!r} to resume from")
            state = read_state_dict(state_path, what="evaluator training state")
            _check_same_data(state, digests, a)
            if state.get("settings") != _settings_dict(settings, a, digests):
                raise ValueError(f"--resume: {STATE_FILENAME} in {a.out!r} was written with other settings "
                                 f"({state.get('settings')}); use the same options (only --epochs may grow)")
            if int(state.get("epoch", 0)) > settings.pretrain_epochs + settings.epochs:
                raise ValueError(f"--resume: {a.out!r} is at epoch {state['epoch']}, past --ae-epochs + --epochs "
                                 f"{settings.pretrain_epochs + settings.epochs}")
        except ValueError as e:
            print(f"smdm evaluator train: error: {e}", file=sys.stderr)
            od.abandon(keep=od.resumed_from == od.path)  # an interrupted run's folder stays as it was
            return 2
    source, say = a.data or "the embedded CMU clips", note_printer(a)
    say(f"smdm evaluator train: {len(train)} training motions ({train.representation}, "
          f"{train.motions[0].shape[1]}-D) from {source}; held out: "
          + (", ".join(f"{s} {len(d)}" for s, d in held.items()) or "none")
          + f"; words: {'GloVe ' + a.glove if a.glove else f'learned ({ev.config.vocab_size} words)'}; "
          f"{ev.mean.device}", flush=True)
    val = held.get("val") or held.get("test")

    saved = [state["epoch"] if state else 0]

    def save_state(st):
        with atomic_open(state_path, "wb") as f:
            torch.save({**st, "settings": _settings_dict(settings, a, digests), "data_digests": digests}, f)
        saved[0] = st["epoch"]

    t0 = time.perf_counter()
    try:
        st = train_evaluator(ev, train, val, settings, state=state, progress=progress_of(a), on_epoch=save_state)
    except KeyboardInterrupt:
        print("\nsmdm evaluator train: interrupted; " + (
            f"rerun with --resume to continue from epoch {saved[0]}" if saved[0] else "no epoch was finished"),
            file=sys.stderr)
        raise
    metrics = {s: held_out_accuracy(ev, d, settings.eval_draws, seed=a.seed) for s, d in held.items()}
    metrics["train"] = held_out_accuracy(ev, train, settings.eval_draws, seed=a.seed)
    check_split = "test" if "test" in held else ("val" if "val" in held else None)
    check = None
    if check_split is not None and len(held[check_split]) >= 4:
        check = retrieval_check(ev, held[check_split], replications=CHECK_REPLICATIONS, seed=a.seed)
    info = {"data": os.path.abspath(a.data) if a.data else "embedded CMU clips", "representation": train.representation,
            "n_train": len(train), "recipe": settings.recipe, "best_epoch": st["best"]["epoch"] - settings.pretrain_epochs,
            "epochs": st["epoch"] - settings.pretrain_epochs, "ae_epochs": settings.pretrain_epochs,
            "train_seconds": st["seconds"], "settings": _settings_dict(settings, a, digests),
            "train_settings": settings.to_dict(),
            "selected_on": "val" if "val" in held else ("test" if held else "last epoch"),
            "metrics": metrics, "retrieval_check": None if check is None else {"split": check_split, **check.to_dict()},
            "history": st["history"]}
    save_evaluator(ev, folder, info)
    atomic_write_json(os.path.join(folder, "metrics.json"), {k: info[k] for k in (
        "metrics", "retrieval_check", "best_epoch", "epochs", "train_seconds", "selected_on")})
    print(f"trained {settings.pretrain_epochs} auto-encoder + {info['epochs']} matching epochs ({settings.recipe}) in "
          f"{st['seconds']:.1f} s (kept matching epoch {info['best_epoch']}, chosen on {info['selected_on']}); wall "
          f"{time.perf_counter() - t0:.1f} s")
    say(f"next: smdm evaluator check {a.out}" + (f" --data {a.data}" if a.data else "")
          + "   (what this evaluator can resolve)")
    print("| split | motions | pool | R-precision top-1 | top-3 | chance top-1 / top-3 | matching score |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for s, m in metrics.items():
        print(f"| {s} | {m['n_motions']} | {m['pool_size']} | {m['top1']:.3f} | {m['top3']:.3f} | "
              f"{m['chance_top1']:.3f} / {m['chance_top3']:.3f} | {m['matching_score']:.3f} |")
    if "val" in held and "test" in held:
        print("(the weights were chosen on val: test is the unbiased number)")
    if check is not None:
        print(f"\n{check_split}, {CHECK_REPLICATIONS} replications of smdm eval's protocol (mean ± 95%): {check.line()}")
        blind = [w for w, ok in (("time-reversed motion", check.sees_order()),
                                  ("swapped captions", check.sees_captions())) if not ok]
        if blind:
            print(f"warning: this evaluator's R-precision does not fall clearly for {' and '.join(blind)}: it cannot "
                  "rank models by how well their motion follows the caption (docs/evaluation.md)", file=sys.stderr)
    spread = recipe_spread(settings, a.glove)
    if spread:
        print("\n" + spread)
    return 0


def recipe_spread(settings: Any, glove: Optional[str]) -> str:
    """What the same recipe gave over several training seeds on the CMU set (the measured table of
    docs/evaluation.md, packaged as :data:`~smdm_plugin.metrics.evaluator.seeds.SEEDS_FILE`), when
    ``settings`` are those it was measured with; else ``""``."""
    from ..metrics.evaluator.seeds import load_seed_table, recipe_of

    table = load_seed_table()
    if table is None or glove is not None or table.settings != recipe_of(settings.to_dict()):
        return ""
    return (f"The same recipe over training seeds {table.seeds} on {table.data} (docs/evaluation.md; held-out "
            f"test, {table.replications} replications each):\n" + table.spread_markdown())


def build_check_parser() -> argparse.ArgumentParser:
    from ..metrics.evaluator.protocol import PROTOCOLS
    from .common.args import add_common_flags, existing_path, int_range, seed_type

    p = argparse.ArgumentParser(
        prog="smdm evaluator check",
        description="The sensitivity table of an evaluator on a split: FID, FID / diversity², R-precision and matching "
                    "score of the real motions degraded (noise 0.1 / 0.3 / 1.0 x Std, 9-frame moving average, time "
                    "reversal, foot sliding, caption swap) beside the real-vs-real floor, under smdm eval's protocol. "
                    "Written to EDIR/sensitivity.json; smdm eval shows it beside every result.")
    p.add_argument("evaluator", metavar="EDIR",   # checked after parsing (positional_type)
                   help="an evaluator folder (trained here, or upstream's finest.tar layout)")
    p.add_argument("--data", type=existing_path("dir"), default=None, metavar="DIR",
                   help="HumanML3D-format folder the evaluator reads (default: the embedded CMU clips)")
    p.add_argument("--split", default="test", help="the split to degrade (default: test)")
    p.add_argument("--glove", type=existing_path("dir"), default=None, metavar="DIR",
                   help="GloVe folder for upstream's evaluator when it is not EDIR/glove")
    p.add_argument("--protocol", choices=PROTOCOLS, default="upstream",
                   help="upstream: per replication, draws of 32 motions with random crops and captions (default); "
                        "fixed: every motion, offset 0")
    p.add_argument("--replications", type=int_range(1, 10000), default=20, help="replications (default: 20)")
    p.add_argument("--seed", type=seed_type, default=0, help="seed of the draws and the noise (default: 0)")
    add_common_flags(p, progress=False, why_not="it shows no progress")
    return p


def run_check(a: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    """``smdm evaluator check``: measure, print and save the table (under EDIR's lock)."""
    from ..io.outdir import OutputLock, OutputLockedError, describe_os_error
    from ..metrics.evaluator.check import save_check, sensitivity
    from ..metrics.evaluator.data import load_split
    from ..metrics.evaluator.model import evaluator_layout, feature_mismatch, load_evaluator
    from .common.args import resolve_device
    from .common.threads import apply_threads

    apply_threads(a.threads)
    try:
        layout = evaluator_layout(a.evaluator)
        ev = load_evaluator(a.evaluator, glove=a.glove, device=resolve_device(a.device))
        data = load_split(a.data, a.split)
    except (FileNotFoundError, ValueError) as e:
        print(f"smdm evaluator check: {e}", file=sys.stderr)
        return 2
    D = data.motions[0].shape[1]
    why = feature_mismatch(ev, layout, data.representation, D)
    if why:
        p.error(f"argument EDIR: {why}, the data ({a.data or 'embedded clips'}) has {data.representation} [{D}]")
    if data.representation not in ("humanml3d", "joints66"):
        p.error(f"argument --data: representation {data.representation!r} has no foot-sliding row")
    say = note_printer(a)
    say(f"smdm evaluator check: {a.evaluator} ({layout}) on {len(data)} {a.split} motions of "
          f"{a.data or 'the embedded CMU clips'}; {a.replications} replications, {a.protocol} protocol", flush=True)
    try:
        with OutputLock(a.evaluator, command="smdm evaluator check", what="EDIR"):
            table = sensitivity(ev, data, replications=a.replications, seed=a.seed, protocol=a.protocol,
                                data_name=os.path.abspath(a.data) if a.data else "embedded CMU clips", split=a.split)
            path = save_check(table, a.evaluator)
    except OutputLockedError as e:
        print(f"smdm evaluator check: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"smdm evaluator check: error: {describe_os_error(e)}", file=sys.stderr)
        return 1
    print("\n" + table.markdown())
    say(f"saved {os.path.abspath(path)}")
    return 0


def settings_from_args(a: argparse.Namespace) -> Any:
    """The :class:`~smdm_plugin.metrics.evaluator.train.TrainSettings` the options ask for (the recipe's
    defaults where an option is not given)."""
    from ..metrics.evaluator.train import TrainSettings

    d = TrainSettings(recipe=a.recipe)
    sizes = dict(d.sizes)
    if a.hidden is not None:
        sizes.update(dim_movement_hidden=a.hidden, dim_movement_latent=a.hidden, dim_motion_hidden=a.hidden,
                     dim_text_hidden=a.hidden)
    if a.dim is not None:
        sizes["dim_coemb"] = a.dim
    if a.reversed_negatives and a.recipe != "t2m":
        raise ValueError("argument --reversed-negatives: only with --recipe t2m (a term of its margin loss)")
    t2m = TrainSettings(recipe="t2m")   # the parser's defaults: a value other than these was given
    for name, what in (("ae_epochs", "its first stage"), ("margin", "its margin loss")):
        if a.recipe != "t2m" and getattr(a, name) != getattr(t2m, name):
            raise ValueError(f"argument --{name.replace('_', '-')}: only with --recipe t2m ({what}); "
                             f"--recipe {a.recipe} has no use for it")
    return TrainSettings(recipe=a.recipe, epochs=a.epochs, batch=a.batch, lr=a.lr, ae_epochs=a.ae_epochs,
                         margin=a.margin, seed=a.seed, sizes=sizes, select=a.select,
                         reversed_negatives=a.reversed_negatives)


def data_digests(train: Any, held: Dict[str, Any]) -> Dict[str, str]:
    """``split/id`` -> sha256 (16 hex digits) of what was read for that motion (features, their
    shape and dtype, captions), plus each split's ``Mean+Std``: the data by content, wherever it
    lies (``--resume`` compares these, not the path)."""
    import hashlib

    import numpy as np

    out: Dict[str, str] = {}
    for split, d in (("train", train), *sorted(held.items())):
        for i, m, caps in zip(d.ids, d.motions, d.captions):
            h = hashlib.sha256(f"{m.shape}{m.dtype}".encode())
            h.update(np.ascontiguousarray(m).tobytes())
            h.update("\0".join(repr(c) for c in caps).encode())
            out[f"{split}/{i}"] = h.hexdigest()[:16]
        h = hashlib.sha256(np.ascontiguousarray(d.mean, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(d.std, dtype=np.float64).tobytes())
        out[f"{split}/Mean+Std"] = h.hexdigest()[:16]
    return out


def _check_same_data(state: Dict[str, Any], digests: Dict[str, str], a: argparse.Namespace) -> None:
    """``ValueError`` naming what changed when the run was trained on other data. Runs saved before
    content digests (0.4) are compared by path."""
    from ..io.files import describe_changes, digests_fingerprint

    saved = (state.get("settings") or {}).get("data")
    old = state.get("data_digests")
    if not isinstance(old, dict):  # a 0.4 run: the data by path
        now = os.path.abspath(a.data) if a.data else None
        if saved != now:
            raise ValueError(f"--resume: {a.out!r} was trained on other data (saved {saved!r}, now {now!r})")
        state["settings"] = {**state["settings"], "data": digests_fingerprint(digests)}
        return
    if digests_fingerprint(old) != digests_fingerprint(digests):
        raise ValueError(f"--resume: {a.out!r} was trained on other data (--data {a.data or 'embedded clips'}: "
                         f"{describe_changes(old, digests)}); resume with the same data, or start a new run")


def _settings_dict(settings, a: argparse.Namespace, digests: Dict[str, str]) -> dict:
    from ..io.files import digests_fingerprint

    return {**{k: v for k, v in settings.to_dict().items() if k not in ("epochs", "eval_draws")},
            "glove": os.path.abspath(a.glove) if a.glove else None,
            "data": digests_fingerprint(digests)}


if __name__ == "__main__":
    sys.exit(main())
