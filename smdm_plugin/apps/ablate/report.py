"""``smdm ablate``'s report: ``results.md`` / ``results.csv`` (one row per variant, the real
validation motions' row for reference) and ``loss_curves.png``."""
from __future__ import annotations

import csv
import math
import os
from typing import Any, Dict, List, Optional

import numpy as np

from ...io.files import atomic_open, atomic_write_text

# ----------------------------------------------------------------------------------------- report
COLUMNS = ("variant", "status", "final loss", "best loss", "val loss", "steps/s", "keyframe error (mm)", "EES (cm/frame)",
           "jitter (m/s³)", "foot skating", "wall (s)")
#: the report's reference row: the real validation motions
REFERENCE_ROW = "real validation motion"


#: the numbers of a variant's ``result.json`` the report shows (each a number or null)
RESULT_NUMBERS = ("final_loss", "best_loss", "val_loss", "steps_per_s", "keyframe_error_mm", "ees", "jitter",
                  "foot_skating", "wall_s")


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def check_record(rec: Dict[str, Any]) -> Optional[str]:
    """Why a result record cannot be reported (a field of :data:`RESULT_NUMBERS` that is not a
    number or null, ``losses`` not a list of numbers), or None when it can."""
    for k in RESULT_NUMBERS:
        if rec.get(k) is not None and not _is_number(rec[k]):
            return f"{k}={rec[k]!r}: expected a number or null"
    losses = rec.get("losses")
    if losses is not None and not (isinstance(losses, list) and all(_is_number(v) for v in losses)):
        return "losses: expected a list of numbers"
    snaps = rec.get("snapshots")  # the quality-versus-compute study's records
    if snaps is not None:
        if not isinstance(snaps, list) or not all(isinstance(x, dict) for x in snaps):
            return "snapshots: expected a list of objects"
        for i, x in enumerate(snaps):
            bad = [k for k, v in x.items() if k != "kind" and v is not None and not _is_number(v)]
            if bad or not isinstance(x.get("kind"), str):
                k = bad[0] if bad else "kind"
                return f"snapshots[{i}].{k}={x.get(k)!r}: expected {'a number or null' if bad else 'a string'}"
    return None


def _fmt(v: Any, spec: str) -> str:
    if not _is_number(v):  # None, or (a record edited by hand) not a number: never a crash
        return "—" if v is None else "?"
    return "—" if isinstance(v, float) and not math.isfinite(v) else format(v, spec)


def write_report(results: List[Dict[str, Any]], out: str, real_ees: Optional[float], cfg: Dict[str, Any],
                 data_fingerprint: Optional[str] = None, real: Optional[Dict[str, Optional[float]]] = None) -> str:
    """``results.md`` / ``results.csv`` / ``loss_curves.png`` of ``results`` (one row per variant;
    numbers only for ``ok`` rows; jitter and foot skating of the variant's unconditional samples),
    then, with ``real`` (``ees``, ``jitter``, ``foot_skating`` of the real validation motions), a
    reference row; returns the markdown."""
    rows = []
    for r in results:
        ok = r.get("status") == "ok"
        rows.append([r["name"], r.get("status", "?"),
                     _fmt(r.get("final_loss") if ok else None, ".4f"), _fmt(r.get("best_loss") if ok else None, ".4f"),
                     _fmt(r.get("val_loss") if ok else None, ".4f"),
                     _fmt(r.get("steps_per_s") if ok else None, ".2f"),
                     _fmt(r.get("keyframe_error_mm") if ok else None, ".1f"),
                     _fmt(r.get("ees") if ok else None, ".3f"),
                     _fmt(r.get("jitter") if ok else None, ".0f"), _fmt(r.get("foot_skating") if ok else None, ".3f"),
                     _fmt(r.get("wall_s") if r.get("status") in ("ok", "failed") else None, ".0f")])
    if real is not None:
        rows.append([REFERENCE_ROW, "reference"] + ["—"] * 5 + [_fmt(real.get("ees"), ".3f"),
                                                                 _fmt(real.get("jitter"), ".0f"),
                                                                 _fmt(real.get("foot_skating"), ".3f"), "—"])
    with atomic_open(os.path.join(out, "results.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        w.writerows(rows)
    lines = [f"{cfg.get('name', 'ablation')}: {cfg['steps']} steps × batch {cfg['batch']}, seed {cfg['seed']}, "
             f"TinyMDM {cfg['model']}, {cfg['diffusion_steps']} diffusion steps; sparse base {cfg.get('sparse')}",
             "", "| " + " | ".join(COLUMNS) + " |", "| --- | --- |" + " ---: |" * (len(COLUMNS) - 2)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    lines.append(f"\nEES of the real validation motions: {_fmt(real_ees, '.3f')} cm/frame "
                 "(generated motions closer to it are better).")
    from ... import __version__

    lines.append(f"\nProvenance: smdm-plugin {__version__}, data {cfg.get('data')}"
                 + (f" (fingerprint {data_fingerprint})" if data_fingerprint else "")
                 + "; per variant in <folder>/result.json.")
    reused = [r["name"] for r in results if r.get("reused")]
    if reused:
        lines.append(f"\nReused from an earlier run with the same provenance: {', '.join(reused)}.")
    for r in results:
        if r.get("status") == "failed":
            lines.append(f"\n{r['name']} failed: {r.get('error')}")
        elif r.get("status") in ("stale", "corrupt"):
            lines.append(f"\n{r['name']}: {r['status']}, not shown ({r.get('reason')}); run it with --only and "
                         "--overwrite.")
    pending = [r["name"] for r in results if r.get("status") == "not run"]
    if pending:
        lines.append(f"\nNot run yet: {', '.join(pending)}.")
    text = "\n".join(lines)
    atomic_write_text(os.path.join(out, "results.md"), text + "\n")
    _plot(results, os.path.join(out, "loss_curves.png"))
    return text


def _plot(results: List[Dict[str, Any]], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5))
    for r in results:
        if r.get("status") != "ok" or not r.get("losses"):
            continue
        loss = np.asarray(r["losses"])
        k = max(1, len(loss) // 20)
        sm = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.plot(np.arange(len(sm)) + k, sm, label=r["name"], lw=1.5 if r["name"].startswith(("dense", "sparse")) else 1)
    ax.set_xlabel("training step")
    ax.set_ylabel("training loss (moving average)")
    ax.set_yscale("log")
    if ax.lines:
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
