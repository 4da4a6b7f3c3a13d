"""``smdm evaluator train``: train a T2M-architecture evaluator on your own captioned motion and
report how far to trust it (held-out R-precision beside the weights).

    smdm evaluator train --data dataset/MyMotion --out evaluators/mine      # HumanML3D layout
    smdm evaluator train --out evaluators/cmu                               # the embedded CMU clips

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
OUTPUTS = ("evaluator.json", "evaluator.pt", "metrics.json", STATE_FILENAME)


from .common.threads import THREADS_HELP


def build_parser() -> argparse.ArgumentParser:
    from ..metrics.evaluator.train import OWN_SIZES, TrainSettings
    from .common.args import add_overwrite, device_type, existing_path, float_range, int_range

    d = TrainSettings()
    p = argparse.ArgumentParser(
        prog="smdm evaluator train",
        description="Train the T2M evaluator's architecture (movement conv encoder, motion and text BiGRUs) "
                    "contrastively on the train split of a HumanML3D-format folder (default: the CMU clips "
                    "embedded in the package), and write its held-out R-precision beside the weights.")
    p.add_argument("--data", type=existing_path("dir"), default=None, metavar="DIR",
                   help="HumanML3D-format folder: new_joint_vecs/, texts/ (caption#word/POS ...#from#to), Mean.npy, "
                        "Std.npy, train.txt (+ val.txt, test.txt for the held-out accuracy); default: the embedded "
                        "CMU clips (joints66 features, CMU's descriptions as captions)")
    p.add_argument("--out", required=True, metavar="EDIR", help="evaluator folder to write")
    p.add_argument("--glove", type=existing_path("dir"), default=None, metavar="DIR",
                   help="T2M's GloVe folder (our_vab_data.npy, our_vab_words.pkl, our_vab_idx.pkl); default: word "
                        "embeddings learned from the training captions")
    p.add_argument("--epochs", type=int_range(1, 100000), default=d.epochs, help=f"passes over the train split (default: {d.epochs})")
    p.add_argument("--batch", type=int_range(2, 4096), default=d.batch, help=f"motions per step (default: {d.batch})")
    p.add_argument("--lr", type=float_range(0.0, lo_open=True), default=d.lr, help=f"Adam (default: {d.lr})")
    p.add_argument("--seed", type=int_range(0), default=d.seed,
                   help=f"seed of the initial weights, the batch order and the caption draws (default: {d.seed})")
    p.add_argument("--dim", type=int_range(4, 4096), default=OWN_SIZES["dim_coemb"],
                   help=f"co-embedding size (default: {OWN_SIZES['dim_coemb']}; upstream's: 512)")
    p.add_argument("--hidden", type=int_range(4, 8192), default=OWN_SIZES["dim_motion_hidden"],
                   help=f"hidden size of every encoder (default: {OWN_SIZES['dim_motion_hidden']}; upstream's: 512 / 1024)")
    p.add_argument("--resume", action="store_true", help=f"continue from --out/{STATE_FILENAME} (to --epochs)")
    add_overwrite(p)
    p.add_argument("--device", type=device_type, default="auto", help="auto (CUDA, else MPS, else CPU), cpu, cuda, mps")
    p.add_argument("--threads", type=int_range(1, 1024), default=None, help=THREADS_HELP)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print("usage: smdm evaluator train [options]   ('smdm evaluator train --help' for the options)",
              file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help"):
        top = argparse.ArgumentParser(prog="smdm evaluator", description="T2M-style text-motion evaluators")
        sub = top.add_subparsers(dest="command", metavar="train")
        sub.add_parser("train", parents=[build_parser()], add_help=False,
                       help="train an evaluator on a HumanML3D-format folder (or the embedded clips)")
        top.parse_args(argv)      # prints the help and exits 0
    if argv[0] != "train":
        print(f"smdm evaluator: error: unknown subcommand {argv[0]!r} (expected: train)", file=sys.stderr)
        return 2
    p = build_parser()
    a = p.parse_args(argv[1:])
    return run(a, p)


def run(a: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    from ..io.files import OutputExistsError
    from ..io.outdir import OutputDir, open_or_refuse
    from ..metrics.evaluator.data import load_split, split_names
    from ..metrics.evaluator.train import OWN_SIZES, TrainSettings, build_evaluator

    from .common.threads import apply_threads

    if a.resume and a.overwrite:
        p.error("argument --overwrite: not allowed with argument --resume")
    apply_threads(a.threads)
    # as smdm train: locked, apart from the inputs, written in .<name>.partial (kept when interrupted, for
    # --resume) and swapped in as one unit; --resume continues an interrupted or a finished run
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
    sizes = dict(OWN_SIZES, dim_coemb=a.dim, dim_movement_hidden=a.hidden, dim_movement_latent=a.hidden,
                 dim_motion_hidden=a.hidden, dim_text_hidden=a.hidden)
    settings = TrainSettings(epochs=a.epochs, batch=a.batch, lr=a.lr, seed=a.seed, sizes=sizes)
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
        print(f"saved {os.path.abspath(a.out)}")
    return status


def _train(a: argparse.Namespace, od: Any, settings: Any, ev: Any, train: Any, held: Dict[str, Any]) -> int:
    """Train ``ev`` (with ``--resume``: from the state in ``od.path``) and write :data:`OUTPUTS` into
    ``od.path``, the partial folder of ``--out`` (an :class:`~smdm_plugin.io.outdir.OutputDir`);
    a refused resume abandons ``od`` and returns 2."""
    import time

    import torch

    from ..io.checkpoint import read_state_dict
    from ..io.files import atomic_open, atomic_write_json
    from ..metrics.evaluator.model import save_evaluator
    from ..metrics.evaluator.train import held_out_accuracy, train_evaluator

    folder = od.path
    state_path = os.path.join(folder, STATE_FILENAME)
    state = None
    if a.resume:
        try:
            if not os.path.isfile(state_path):
                raise ValueError(f"--resume: no {STATE_FILENAME} in {a.out!r} to resume from")
            state = read_state_dict(state_path, what="evaluator training state")
            if state.get("settings") != _settings_dict(settings, a):
                raise ValueError(f"--resume: {STATE_FILENAME} in {a.out!r} was written with other settings "
                                 f"({state.get('settings')}); use the same options (only --epochs may grow)")
            if int(state.get("epoch", 0)) > settings.epochs:
                raise ValueError(f"--resume: {a.out!r} is at epoch {state['epoch']}, past --epochs {settings.epochs}")
        except ValueError as e:
            print(f"smdm evaluator train: error: {e}", file=sys.stderr)
            od.abandon(keep=od.resumed_from == od.path)  # an interrupted run's folder stays as it was
            return 2
    source = a.data or "the embedded CMU clips"
    print(f"smdm evaluator train: {len(train)} training motions ({train.representation}, "
          f"{train.motions[0].shape[1]}-D) from {source}; held out: "
          + (", ".join(f"{s} {len(d)}" for s, d in held.items()) or "none")
          + f"; words: {'GloVe ' + a.glove if a.glove else f'learned ({ev.config.vocab_size} words)'}; "
          f"{ev.mean.device}", flush=True)
    val = held.get("val") or held.get("test")

    saved = [state["epoch"] if state else 0]

    def save_state(st):
        with atomic_open(state_path, "wb") as f:
            torch.save({**st, "settings": _settings_dict(settings, a)}, f)
        saved[0] = st["epoch"]

    t0 = time.perf_counter()
    try:
        st = train_evaluator(ev, train, val, settings, state=state, progress=not a.no_progress, on_epoch=save_state)
    except KeyboardInterrupt:
        print("\nsmdm evaluator train: interrupted; " + (
            f"rerun with --resume to continue from epoch {saved[0]}" if saved[0] else "no epoch was finished"),
            file=sys.stderr)
        raise
    metrics = {s: held_out_accuracy(ev, d, settings.eval_draws, seed=a.seed) for s, d in held.items()}
    metrics["train"] = held_out_accuracy(ev, train, settings.eval_draws, seed=a.seed)
    info = {"data": os.path.abspath(a.data) if a.data else "embedded CMU clips", "representation": train.representation,
            "n_train": len(train), "best_epoch": st["best"]["epoch"], "epochs": st["epoch"],
            "train_seconds": st["seconds"], "settings": _settings_dict(settings, a),
            "selected_on": "val" if "val" in held else ("test" if held else "last epoch"),
            "metrics": metrics, "history": st["history"]}
    save_evaluator(ev, folder, info)
    atomic_write_json(os.path.join(folder, "metrics.json"), {k: info[k] for k in ("metrics", "best_epoch", "epochs",
                                                                                  "train_seconds", "selected_on")})
    print(f"trained {st['epoch']} epochs in {st['seconds']:.1f} s (kept epoch {st['best']['epoch']}, "
          f"chosen on {info['selected_on']}); wall {time.perf_counter() - t0:.1f} s")
    print("| split | motions | pool | R-precision top-1 | top-3 | chance top-1 / top-3 | matching score |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for s, m in metrics.items():
        print(f"| {s} | {m['n_motions']} | {m['pool_size']} | {m['top1']:.3f} | {m['top3']:.3f} | "
              f"{m['chance_top1']:.3f} / {m['chance_top3']:.3f} | {m['matching_score']:.3f} |")
    if "val" in held and "test" in held:
        print("(the weights were chosen on val: test is the unbiased number)")
    return 0


def _settings_dict(settings, a: argparse.Namespace) -> dict:
    return {"batch": settings.batch, "lr": settings.lr, "seed": settings.seed, "temperature": settings.temperature,
            "sizes": settings.sizes, "glove": os.path.abspath(a.glove) if a.glove else None,
            "data": os.path.abspath(a.data) if a.data else None}


if __name__ == "__main__":
    sys.exit(main())
