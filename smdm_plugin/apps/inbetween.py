"""``smdm inbetween``: sample a motion that passes through your keyframes, with dense and sparse
models side by side, and watch it (GIF).

    smdm demo --out smdm_out/demo                       # trains smdm_out/demo/{dense,sparse}
    smdm inbetween --keyframes clip.bvh --frames 0 30 60 90 119
    smdm inbetween --model results/inbetween/models/humanml3d-dense results/inbetween/models/humanml3d-sparse \\
        --keyframes new_joint_vecs/000003.npy --every 20

Keyframes come from a motion file (``--keyframes``): frames picked from a clip (``--frames``, or one
every ``--every`` frames), or a file of K poses placed at the K frames of ``--frames``. What a model
accepts depends on its representation (see :mod:`smdm_plugin.io.representation`):

* ``joints66`` models (``smdm demo``): a ``.bvh`` (CMU skeleton), joints ``[N, 22, 3]`` in metres,
  or HumanML3D features ``[N, 263]`` (converted to joints); keyframes are imposed exactly, global
  position included;
* ``humanml3d`` models: HumanML3D features ``[N, 263]`` (un-normalised, as ``new_joint_vecs``);
  the 263 values of each keyframe are imposed exactly, its global position follows from the
  generated root velocities before it.

The keyframes are imposed by imputation at every diffusion step (``--imputation``) and, for sparse
models, are keyframe tokens of the sparse transformer (``--forced``). Writes to ``--out``: one
``<model>_joints.npy`` ``[S, N, 22, 3]`` and ``<model>_features.npy`` ``[S, N, D]`` per model,
``keyframes.json``, ``summary.md`` / ``summary.json`` (keyframe error, jitter) and ``inbetween.gif``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch

from ..adapters.inbetween import POLICIES
from ..reference.diffusion import IMPUTATIONS
from ..metrics.inbetween import keyframe_metrics
from ._args import add_overwrite, device_type, int_range
from .threads import THREADS_HELP
from .motion_files import ACCEPTED, LoadedMotion, add_motion_file_options

DEFAULT_MODELS = (os.path.join("smdm_out", "demo", "dense"), os.path.join("smdm_out", "demo", "sparse"))


@dataclass
class Keyframes:
    """Where the keyframes go: ``frames`` (output indices, sorted) of an ``length``-frame output;
    ``source_frames`` the matching frames of the source file; ``segment`` the source frames
    ``[start, start + length)`` when the source covers them (the reference motion), else None."""

    frames: List[int]
    source_frames: List[int]
    length: int
    start: int
    placed: bool

    def segment(self, n_source: int) -> Optional[slice]:
        return None if self.placed or self.start + self.length > n_source else slice(self.start, self.start + self.length)


def plan_keyframes(n_source: int, frames: Optional[Sequence[int]], every: Optional[int], start: Optional[int],
                   length: Optional[int], max_frames: int) -> Keyframes:
    """Resolve ``--frames`` / ``--every`` / ``--start`` / ``--length`` against a source of
    ``n_source`` frames; ValueError with the option's name when they do not fit."""
    if frames:
        fr = sorted(set(int(f) for f in frames))
        if len(fr) != len(frames):
            raise ValueError(f"--frames: repeated frames in {list(frames)}")
        placed = len(fr) == n_source and fr[-1] >= n_source
        if placed:
            if list(frames) != fr:
                raise ValueError("--frames: give increasing frames (one per pose of the file, in order)")
            if start not in (None, 0):
                raise ValueError("--start: not used when poses are placed at --frames")
            start = 0
        elif fr[-1] >= n_source:
            raise ValueError(f"--frames: frame {fr[-1]} is beyond the {n_source} frames of the keyframe file "
                             f"(to place K poses, give K frames)")
        start = fr[0] if start is None else start
        if start > fr[0]:
            raise ValueError(f"--start {start} is after the first keyframe {fr[0]}")
        need = fr[-1] - start + 1
        length = need if length is None else length
        if length < need:
            raise ValueError(f"--length {length} is too short for keyframes up to frame {fr[-1]} from --start {start}")
        out = Keyframes([f - start for f in fr], list(range(len(fr))) if placed else fr, length, start, placed)
    else:
        start = 0 if start is None else start
        if start >= n_source:
            raise ValueError(f"--start {start} is beyond the {n_source} frames of the keyframe file")
        length = min(n_source - start, max_frames) if length is None else length
        if start + length > n_source:
            raise ValueError(f"--length {length} from --start {start} runs past the {n_source} frames of the "
                             "keyframe file")
        rel = sorted(set(range(0, length, every or 20)) | {length - 1})
        out = Keyframes(rel, [start + f for f in rel], length, start, False)
    if out.length > max_frames:
        raise ValueError(f"--length {out.length} exceeds the {max_frames} frames the model was trained on")
    if out.length < 2:
        raise ValueError(f"--length must be >= 2, got {out.length}")
    return out


@dataclass
class Result:
    """One model's in-betweens: ``features [S, N, D]`` (un-normalised), ``joints [S, N, 22, 3]``
    (metres, in the keyframe file's frame), ``target [N, 22, 3]`` the joints the keyframes come
    from (their segment of the file when it covers the output, else only keyframe frames are valid),
    ``feature_error`` max |output - keyframe| over the keyframes' features, ``seconds`` of sampling."""

    label: str
    features: np.ndarray
    joints: np.ndarray
    target: np.ndarray
    feature_error: float
    seconds: float


def model_inputs(bundle: Any, source: LoadedMotion, kf: Keyframes) -> tuple:
    """``(features [N, D] un-normalised, target joints [N, 22, 3], xz offset [3])`` for ``bundle``'s
    representation: the source's frames ``[start, start + length)`` (placed poses: at the keyframes,
    zeros elsewhere); ValueError when the source cannot give that representation."""
    rep = bundle.representation
    N, D = kf.length, rep.dim
    src = np.asarray(kf.source_frames)
    dst = np.asarray(kf.frames)
    feats = np.zeros((N, D), np.float32)
    if rep.name == "humanml3d":
        if source.kind != "humanml3d":
            raise ValueError(f"{bundle.path} is a HumanML3D (263-D) model: give the keyframes as HumanML3D "
                             f"features .npy [N, 263], got {source.kind} from {source.source}")
        feats[dst] = source.features[src]
        seg = kf.segment(len(source.features))
        ref = rep.to_joints(source.features[seg] if seg else feats)  # segment re-integrated from its frame 0
        return feats, np.asarray(ref, np.float32), np.zeros(3, np.float32)
    if not source.humanml22:
        raise ValueError(f"{source.source}: {source.joints.shape[1]} joints; a joints66 model needs HumanML3D's "
                         "22 joints (a CMU BVH, joints [N, 22, 3] or features [N, 263])")
    joints = np.asarray(source.joints, np.float32)
    offset = joints[src[0], 0].copy()
    offset[1] = 0.0
    feats[dst] = rep.from_joints(joints[src] - offset)
    seg = kf.segment(len(joints))
    ref = joints[seg] if seg else rep.to_joints(feats) + offset
    return feats, np.asarray(ref, np.float32), offset


def run_inbetween(bundle: Any, source: LoadedMotion, kf: Keyframes, samples: int = 1, seed: int = 0,
                  imputation: str = "x0", policy: str = "ends", device: Any = "cpu",
                  progress: bool = False) -> Result:
    """Sample ``samples`` in-betweens from ``bundle`` (:class:`~smdm_plugin.io.bundle.ModelBundle`)."""
    from ..adapters.inbetween import keyframe_constraint, sample_inbetween

    feats, target, offset = model_inputs(bundle, source, kf)
    x = bundle.normalise(torch.from_numpy(feats)).to(device).unsqueeze(0).expand(samples, -1, -1)
    constraint = keyframe_constraint(x.contiguous(), kf.frames)
    gen = torch.Generator(device=device).manual_seed(seed)
    bundle.model.to(device).eval()
    t0 = time.perf_counter()
    out = sample_inbetween(bundle.model, bundle.diffusion, constraint, imputation=imputation, policy=policy,
                           generator=gen, progress=progress)
    seconds = time.perf_counter() - t0
    out = bundle.denormalise(out.float()).cpu().numpy()
    err = float(np.abs(out[:, kf.frames] - feats[kf.frames][None]).max())
    joints = np.asarray(bundle.representation.to_joints(out), np.float32) + offset
    return Result(bundle.label, out, joints, target, err, seconds)


COLUMNS = (("keyframe feature error (max)", "feature_error", "{:.2g}"),
           ("keyframe error (mm)", "keyframe_error_mm", "{:.1f}"),
           ("root-relative keyframe error (mm)", "keyframe_error_root_relative_mm", "{:.1f}"),
           ("jitter at transitions (m/s³)", "jitter_transitions", "{:.0f}"),
           ("jitter (m/s³)", "jitter", "{:.0f}"),
           ("foot skating", "foot_skating", "{:.3f}"),
           ("in-between error vs source (mm)", "inbetween_error_mm", "{:.0f}"),
           ("sampling (s)", "seconds", "{:.2f}"))


def summary_markdown(rows: List[Dict[str, Any]]) -> str:
    cols = [c for c in COLUMNS if any(c[1] in r for r in rows)]
    lines = ["| model | " + " | ".join(c[0] for c in cols) + " |", "| --- |" + " ---: |" * len(cols)]
    for r in rows:
        lines.append(f"| {r['model']} | " + " | ".join(c[2].format(r[c[1]]) if c[1] in r else "—" for c in cols) + " |")
    ref = next((r for r in rows if "reference_jitter" in r), None)
    if ref:
        lines.append(f"\nthe source motion: jitter {ref['reference_jitter']:.0f} m/s³, at the transitions "
                     f"{ref['reference_jitter_transitions']:.0f} m/s³, foot skating {ref['reference_foot_skating']:.3f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smdm inbetween", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="keyframe files: " + ACCEPTED)
    p.add_argument("--model", nargs="+", default=None, metavar="DIR",
                   help="model folders (smdm demo writes OUT/dense and OUT/sparse; default: "
                        + " ".join(DEFAULT_MODELS) + ")")
    p.add_argument("--keyframes", required=True, metavar="FILE", help=".bvh or .npy motion holding the keyframes")
    p.add_argument("--frames", nargs="+", type=int_range(0), default=None, metavar="F",
                   help="keyframe frames of the file (0-based); with a file of K poses, the K output frames")
    p.add_argument("--every", type=int_range(1), default=None, help="a keyframe every EVERY frames (default 20)")
    p.add_argument("--start", type=int_range(0), default=None, help="first frame of the file to in-between from")
    p.add_argument("--length", type=int_range(2, 1000), default=None, help="frames to generate")
    p.add_argument("--samples", type=int_range(1, 64), default=1, help="in-betweens per model (default 1)")
    p.add_argument("--seed", type=int_range(0), default=0, help="random seed of the sampling noise (default 0)")
    p.add_argument("--imputation", choices=IMPUTATIONS, default="x0",
                   help="how keyframes are imposed at each step: x0 = the clean prediction (MDM's edit mode), "
                        "xt = the noisy motion")
    p.add_argument("--forced", choices=POLICIES, default="ends",
                   help="which keyframes are tokens of a sparse model: ends of each run of consecutive "
                        "keyframes (default), all, none")
    add_motion_file_options(p)
    p.add_argument("--out", default=os.path.join("smdm_out", "inbetween"), help="output folder")
    p.add_argument("--no-gif", action="store_true", help="skip the animation")
    p.add_argument("--device", type=device_type, default="auto", help="auto (CUDA, else MPS, else CPU), cpu, cuda, cuda:N or mps (default auto)")
    p.add_argument("--threads", type=int_range(1, 256), default=None, help=THREADS_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_overwrite(p)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    from ..io.bundle import load_bundle
    from ..io.files import OutputExistsError
    from ..io.outdir import OutputDir, check_no_overlap
    from ._args import resolve_device
    from .motion_files import load_motion

    p = build_parser()
    a = p.parse_args(argv)
    if a.frames and a.every:
        p.error("--frames and --every: give one of them")
    from .threads import apply_threads
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
    inputs = {"--keyframes": a.keyframes, **{f"--model {m}": m for m in models}}
    try:
        check_no_overlap(a.out, inputs)
    except OutputExistsError as e:
        p.error(str(e))
    fps = bundles[0].fps
    try:
        source = load_motion(a.keyframes, fps=fps, sample=a.sample, allow_pickle=a.allow_pickle)
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
    print(f"smdm inbetween: {len(kf.frames)} keyframes {how} of {a.keyframes} "
          f"({source.kind}) -> {kf.length} frames at {fps:g} fps on {dev}; imputation {a.imputation}, "
          f"forced keyframes: {a.forced}")
    rows, results = [], []
    for name, b in zip(names, bundles):
        res = run_inbetween(b, source, kf, a.samples, a.seed, a.imputation, a.forced, dev, progress=not a.quiet)
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
        from .animation import Panel, render_gif

        panels = []
        if kf.segment(len(source.joints)) is not None:
            panels.append(Panel(results[0].target, "keyframe source", kf.frames))
        panels += [Panel(r.joints[0], f"{n}: {r.label}", kf.frames) for n, r in zip(names, results)]
        render_gif(panels, os.path.join(out, "inbetween.gif"), fps=fps, overwrite=True, progress=not a.quiet,
                   suptitle=f"in-betweening {len(kf.frames)} keyframes (red) of {os.path.basename(a.keyframes)}")
    print(f"outputs: {os.path.abspath(a.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
