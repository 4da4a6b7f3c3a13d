"""``smdm inbetween``: sample a motion that passes through your keyframes, with dense and sparse
models side by side, and watch it (GIF)."""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any, List, Optional

import numpy as np
import torch

from ..adapters.inbetween_sampling import POLICIES
from ..reference.simple_diffusion import IMPUTATIONS
from ..metrics.inbetween_metrics import keyframe_metrics
from .common.args import (add_common_flags, add_overwrite, existing_path, int_range, note_printer, output_path,
                          progress_of, seed_type)
from .common.bundle_inbetween import model_inputs, plan_keyframes, run_inbetween, summary_markdown
from .common.motion_files import ACCEPTED, add_motion_file_options

DEFAULT_MODELS = (os.path.join("smdm_out", "demo", "dense"), os.path.join("smdm_out", "demo", "sparse"))


# --------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smdm inbetween", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="keyframe files: " + ACCEPTED)
    p.add_argument("--model", nargs="+", default=None, metavar="DIR",
                   help="model folders (smdm demo writes OUT/dense and OUT/sparse; default: "
                        + " ".join(DEFAULT_MODELS) + ")")
    p.add_argument("--keyframes", required=True, metavar="FILE", type=existing_path("file"),
                   help=".bvh or .npy motion holding the keyframes")
    p.add_argument("--frames", nargs="+", type=int_range(0), default=None, metavar="F",
                   help="keyframe frames of the file (0-based); with a file of K poses, the K output frames")
    p.add_argument("--every", type=int_range(1), default=None, help="a keyframe every EVERY frames (default 20)")
    p.add_argument("--start", type=int_range(0), default=None, help="first frame of the file to in-between from")
    p.add_argument("--length", type=int_range(2, 1000), default=None, help="frames to generate")
    p.add_argument("--samples", type=int_range(1, 64), default=1, help="in-betweens per model (default 1)")
    p.add_argument("--seed", type=seed_type, default=0, help="random seed of the sampling noise (default 0)")
    p.add_argument("--imputation", choices=IMPUTATIONS, default="x0",
                   help="how keyframes are imposed at each step: x0 = the clean prediction (MDM's edit mode), "
                        "xt = the noisy motion")
    p.add_argument("--forced", choices=POLICIES, default="ends",
                   help="which keyframes are tokens of a sparse model: ends of each run of consecutive "
                        "keyframes (default), all, none")
    add_motion_file_options(p)
    p.add_argument("--out", default=os.path.join("smdm_out", "inbetween"), type=output_path(), help="output folder")
    p.add_argument("--no-gif", action="store_true", help="skip the animation")
    add_common_flags(p)
    add_overwrite(p)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    from ..training.bundle import load_bundle
    from ..io.files import OutputExistsError
    from ..io.outdir import OutputDir, check_no_overlap
    from .common.args import resolve_device
    from .common.motion_files import load_motion, rate_differs

    p = build_parser()
    a = p.parse_args(argv)
    if a.frames and a.every:
        p.error("--frames and --every: give one of them")
    from .common.threads import apply_threads
    apply_threads(a.threads)
    dev = resolve_device(a.device)
    models = a.model or [d for d in DEFAULT_MODELS if os.path.isdir(d)]
    if not models:
        p.error("--model: no model folder given and none at " + " / ".join(DEFAULT_MODELS)
                + "; train one with `smdm demo` (writes smdm_out/demo/dense and .../sparse)")
    if os.path.isdir(a.out) and os.listdir(a.out) and not a.overwrite:
        p.error(f"--out {a.out!r} exists and is not empty; pass --overwrite to write into it")
    try:
        bundles = [load_bundle(m, device=dev) for m in models]
    except (OSError, ValueError, RuntimeError) as e:
        p.error(f"--model: {str(e).splitlines()[0]}")
    if a.forced != p.get_default("forced") and not any(b.sparse for b in bundles):
        p.error(f"--forced {a.forced}: applies to sparse models only (which keyframes are their tokens); every "
                "--model is dense")
    inputs = {"--keyframes": a.keyframes, **{f"--model {m}": m for m in models}}
    try:
        check_no_overlap(a.out, inputs)
    except OutputExistsError as e:
        p.error(str(e))
    fps = bundles[0].fps
    try:
        source = load_motion(a.keyframes, fps=fps, sample=a.sample, allow_pickle=a.allow_pickle)
        differs = rate_differs(source, fps)
        if differs:  # keyframes at another rate would be placed at the wrong times
            raise ValueError(f"--keyframes: {differs}, the models' rate")
        kf = plan_keyframes(len(source.joints), a.frames, a.every, a.start, a.length,
                            min(b.max_frames for b in bundles))
        for b in bundles:
            model_inputs(b, source, kf)  # every model can read these keyframes
    except (OSError, ValueError) as e:
        p.error(str(e).splitlines()[0])
    # locked for the run, written in a partial folder, swapped in as one unit when everything is written
    od = OutputDir(a.out, overwrite=a.overwrite, inputs=inputs, command="smdm inbetween")
    try:
        od.open()
    except OutputExistsError as e:
        p.error(str(e))
    with od:
        return _write(a, od.path, bundles, source, kf, dev, fps)


def _write(a: argparse.Namespace, out: str, bundles: List[Any], source: Any, kf: Any, dev: torch.device,
           fps: float) -> int:
    """Run every model and write the outputs into ``out`` (the partial folder of ``--out``)."""
    from ..io.files import atomic_open, atomic_write_json, atomic_write_text

    models = a.model or [d for d in DEFAULT_MODELS if os.path.isdir(d)]
    names = [os.path.basename(os.path.normpath(m)) or f"model{i}" for i, m in enumerate(models)]
    names = [n if names.count(n) == 1 else f"{n}{i}" for i, n in enumerate(names)]
    how = f"placed at frames {kf.frames}" if kf.placed else f"from frames {kf.source_frames}"
    say = note_printer(a)
    say(f"smdm inbetween: {len(kf.frames)} keyframes {how} of {a.keyframes} "
          f"({source.kind}) -> {kf.length} frames at {fps:g} fps on {dev}; imputation {a.imputation}, "
          f"forced keyframes: {a.forced}")
    rows, results = [], []
    for name, b in zip(names, bundles):
        res = run_inbetween(b, source, kf, a.samples, a.seed, a.imputation, a.forced, dev, progress=progress_of(a))
        results.append(res)
        seg = kf.segment(len(source.joints)) is not None
        known = seg or b.representation.name != "humanml3d"  # placed 263-D poses: no global position
        given = np.zeros(kf.length, bool)
        given[kf.frames] = True
        row = {"model": f"{name}: {res.label}", "folder": b.path, "feature_error": res.feature_error,
               "seconds": res.seconds,
               **keyframe_metrics(res.joints, res.target, given, fps, reference=seg, global_error=known)}
        rows.append(row)
        for suffix, arr in (("joints", res.joints), ("features", res.features)):
            with atomic_open(os.path.join(out, f"{name}_{suffix}.npy"), "wb") as f:
                np.save(f, arr)
    table = summary_markdown(rows)
    print(table)
    atomic_write_text(os.path.join(out, "summary.md"), table + "\n")
    atomic_write_json(os.path.join(out, "summary.json"), {"rows": rows, "settings": vars(a)})
    atomic_write_json(os.path.join(out, "keyframes.json"), {
        "source": a.keyframes, "kind": source.kind, "frames": kf.frames, "source_frames": kf.source_frames,
        "start": kf.start, "length": kf.length, "placed": kf.placed, "fps": fps})
    if not a.no_gif:
        from .common.animation import Panel, render_gif

        panels = []
        if kf.segment(len(source.joints)) is not None:
            panels.append(Panel(results[0].target, "keyframe source", kf.frames))
        panels += [Panel(r.joints[0], f"{n}: {r.label}", kf.frames) for n, r in zip(names, results)]
        render_gif(panels, os.path.join(out, "inbetween.gif"), fps=fps, overwrite=True, progress=progress_of(a),
                   suptitle=f"in-betweening {len(kf.frames)} keyframes (red) of {os.path.basename(a.keyframes)}")
    say(f"outputs: {os.path.abspath(a.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
