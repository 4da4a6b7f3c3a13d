"""The motion evaluator of ``smdm demo``: FID and diversity of the demo's unconditional samples.

``smdm demo --evaluator EDIR`` uses an evaluator folder (either layout, :func:`load_demo_evaluator`
checks it reads the demo's ``joints66`` features); without it the demo trains a small one on its own
training clips with the function ``smdm evaluator train`` uses
(:func:`~smdm_plugin.metrics.evaluator.train.train_evaluator`, :func:`train_demo_evaluator`) and saves
it as ``OUT/evaluator/`` (``--evaluator OUT/evaluator`` reuses it). The demo's models are
unconditional, so R-precision and matching score (text against motion) are not reported.
"""
from __future__ import annotations

import os
import time
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

#: the representation the demo's models generate, and its feature width
DEMO_REPRESENTATION, DEMO_WIDTH = "joints66", 66
#: the demo's own evaluator: training windows (frames, stride) and epochs (normal, --quick)
WINDOW, STRIDE, EPOCHS, QUICK_EPOCHS = 40, 8, 15, 2
#: fraction of each training clip's frames in the evaluator's train split (the rest: its val split)
TRAIN_PART = 0.8


def check_demo_evaluator(ev: Any, where: str) -> None:
    """ValueError (one line naming ``where``) unless ``ev`` reads ``joints66`` features ``[N, 66]``."""
    c = ev.config
    if c.representation != DEMO_REPRESENTATION or c.dim_pose != DEMO_WIDTH:
        raise ValueError(f"{where}: the evaluator reads {c.representation} features of width {c.dim_pose}; the demo's "
                         f"models generate {DEMO_REPRESENTATION} of width {DEMO_WIDTH} (train one with "
                         "'smdm evaluator train', whose default data are the demo's clips)")


def load_demo_evaluator(path: str, device: Any = "cpu") -> Any:
    """The evaluator folder ``path`` checked by :func:`check_demo_evaluator`; ValueError /
    FileNotFoundError (one line) otherwise."""
    from ...metrics.evaluator.model import load_evaluator

    try:
        ev = load_evaluator(path, device=device)
    except (OSError, RuntimeError, KeyError) as e:
        raise ValueError(f"{path!r} cannot be read ({' '.join(str(e).split())})") from None
    check_demo_evaluator(ev, repr(path))
    return ev


def train_demo_evaluator(clips: Sequence[Tuple[str, np.ndarray]], folder: str, seed: int, quick: bool = False,
                         device: Any = "cpu", progress: bool = False) -> Tuple[Any, Dict[str, Any]]:
    """Train the demo's evaluator on ``clips`` ``[(name, joints [T, 22, 3] metres, 20 fps)]``: 40-frame
    ``joints66`` windows (every 8 frames) of the first 80% of every clip (train) and of the rest (val,
    when a clip has 40 frames there), captioned with CMU's description of the clip (else its name),
    :data:`EPOCHS` (``quick``: :data:`QUICK_EPOCHS`) epochs, seeded; saves it to ``folder``. Returns
    ``(evaluator, info)``; ``info`` holds the held-out accuracy (``metrics``), sizes and seconds."""
    from ...io.embedded import embedded_descriptions
    from ...metrics.evaluator.data import clips_captioned
    from ...metrics.evaluator.model import save_evaluator
    from ...metrics.evaluator.train import TrainSettings, build_evaluator, train_evaluator

    t0 = time.perf_counter()
    desc = embedded_descriptions()
    train = clips_captioned(clips, desc, (0.0, TRAIN_PART), WINDOW, STRIDE, what="smdm demo: no clip has 40 frames "
                            "for the evaluator; pass --no-evaluator or --evaluator EDIR")
    try:
        val: Optional[Any] = clips_captioned(clips, desc, (TRAIN_PART, 1.0), WINDOW, STRIDE)
    except ValueError:
        val = None
    settings = TrainSettings(epochs=QUICK_EPOCHS if quick else EPOCHS, seed=seed)
    ev = build_evaluator(train, settings).to(device)
    st = train_evaluator(ev, train, None, settings, progress=progress)  # last epoch: val is too small to choose on
    held = {"val": val} if val is not None else {}
    texts = sorted({c[0].text for c in train.captions})
    metrics = {s: caption_accuracy(ev, d, texts) for s, d in held.items()}
    metrics["train"] = caption_accuracy(ev, train, texts)
    info = {"data": "smdm demo training clips: " + ", ".join(n for n, _ in clips), "representation": DEMO_REPRESENTATION,
            "n_train": len(train), "n_val": len(val) if val is not None else 0, "window": WINDOW, "stride": STRIDE,
            "train_part": TRAIN_PART, "captions": len({c[0].text for c in train.captions}),
            "best_epoch": st["best"]["epoch"], "epochs": st["epoch"], "train_seconds": st["seconds"],
            "selected_on": "last epoch", "metrics": metrics, "history": st["history"],
            "settings": {"batch": settings.batch, "lr": settings.lr, "seed": seed, "temperature": settings.temperature,
                         "sizes": settings.sizes}}
    save_evaluator(ev, folder, info)
    info["seconds"] = time.perf_counter() - t0
    return ev, info


def caption_accuracy(ev: Any, data: Any, texts: Sequence[str]) -> Dict[str, Any]:
    """How often a window of ``data`` (:class:`~smdm_plugin.metrics.evaluator.data.CaptionedMotions`,
    one caption each, among ``texts``) is nearer its own caption than the other distinct captions
    ``texts`` (Euclidean, in the co-embedding): ``top1``, ``top3``, ``pool_size`` (len(texts)), chance.
    Windows of one clip share a caption, so the T2M R-precision (a window's caption against 31 others,
    duplicates included) is capped by ties; this is the same retrieval over distinct captions."""
    from ...metrics.evaluator.score import embed_captions, embed_motions
    from ...io.captions import plain_tokens

    texts = list(texts)
    t = embed_captions(ev, [plain_tokens(x) for x in texts])               # [K, C]
    m = embed_motions(ev, data.motions)                                    # [W, C]
    d = np.linalg.norm(m[:, None, :] - t[None, :, :], axis=-1)             # [W, K]
    own = np.array([texts.index(c[0].text) for c in data.captions])
    rank = (d < d[np.arange(len(own)), own][:, None]).sum(1)               # captions strictly nearer
    K = len(texts)
    return {"top1": float(np.mean(rank < 1)), "top3": float(np.mean(rank < 3)), "pool_size": K,
            "n_motions": len(own), "chance_top1": 1.0 / K, "chance_top3": min(1.0, 3.0 / K)}


def evaluator_note(info: Dict[str, Any], source: str, pool: int, pool_clips: Sequence[str], samples: int,
                   floor: Optional[float]) -> str:
    """What the FID column is relative to, in words (appended to training.md)."""
    m = info.get("metrics", {})
    held = m.get("val") or m.get("test")
    acc = (f"its held-out caption retrieval top-1 / top-3 (a window's nearest caption among the distinct ones) {held['top1']:.2f} / {held['top3']:.2f} (pool {held['pool_size']}, "
           f"chance {held['chance_top1']:.2f} / {held['chance_top3']:.2f}; {held['n_motions']} windows)"
           if held else "no held-out accuracy (no clip long enough for a val window)")
    floor_txt = "" if floor is None else (f" FID of {samples} real crops drawn from that pool (seeded) against the "
                                          f"whole pool: **{floor:.3f}**, the floor at this sample size.")
    return (f"FID (and diversity: mean distance of 300 or N−1 random pairs) in the co-embedding of {source}; "
            f"{acc}. FID compares each model's {samples} samples with the {pool} real training crops the models "
            f"trained on ({len(pool_clips)} clip(s): {', '.join(pool_clips)}); the motion capture row scores the "
            f"reference clip's windows against the same pool.{floor_txt} With a few clips and a small evaluator "
            "this FID is a rough indicator, not comparable with published HumanML3D numbers. R-precision and "
            "matching score are not reported: the demo's models are unconditional (no caption to retrieve).")
