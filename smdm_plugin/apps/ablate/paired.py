"""Paired differences of a quality-versus-compute study, read from its result files."""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

RESULTS_FILE = "results.json"
#: the pair compared by default: (baseline, treatment)
PAIR = ("dense", "sparse (VW)")
#: (key, label, direction): the metrics of the paired tables; direction ``-1`` lower is better,
#: ``+1`` higher, ``0`` closer to the real motion's value
METRICS: Tuple[Tuple[str, str, int], ...] = (
    ("fid", "FID", -1), ("r_precision_top1", "R@1", 1), ("r_precision_top3", "R@3", 1),
    ("matching_score", "MM-Dist", -1), ("jitter_per_speed", "j/s (1/s²)", 0), ("jitter", "jitter (m/s³)", 0),
    ("speed", "speed (m/s)", 0), ("foot_skating", "skating", -1))
#: a snapshot: (kind, at) with kind "steps" or "seconds"
Snap = Tuple[str, float]


class ResultsError(ValueError):
    """A study's ``results.json`` that cannot be read: the message names the file and what was expected."""


# ----------------------------------------------------------------------------------------- reading
def _fail(path: str, what: str) -> ResultsError:
    return ResultsError(f"{path}: {what}")


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def read_results(folder: str, metrics: Sequence[str] = tuple(m for m, _, _ in METRICS)) -> Dict[str, Any]:
    """``folder/results.json`` checked for what the paired tables read: a JSON object with ``config``
    (``name``, ``diffusion_steps``), ``runs`` (variant -> list of run records: ``seed`` an int,
    ``status``, ``snapshots`` of objects with ``kind``, ``at``, ``step`` and every metric of
    ``metrics`` a number; NaN allowed, null not) and ``reference`` (an object). Only the runs with
    status ``ok`` are checked: a failed run has no snapshots."""
    path = os.path.join(folder, RESULTS_FILE) if os.path.isdir(folder) or not folder.endswith(".json") else folder
    if not os.path.isfile(path):
        raise _fail(path, "no such file; expected the results.json that smdm ablate --config <study> --out "
                          f"{folder} writes")
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise _fail(path, f"not readable as JSON ({' '.join(str(e).split())})") from None
    expected = "a JSON object with 'config', 'runs' and 'reference' (smdm ablate's study results)"
    if not isinstance(d, dict):
        raise _fail(path, f"holds a {type(d).__name__}; expected {expected}")
    missing = [k for k in ("config", "runs", "reference") if k not in d]
    if missing:
        raise _fail(path, f"has no {', '.join(repr(k) for k in missing)}; expected {expected}")
    cfg, runs = d["config"], d["runs"]
    if not isinstance(cfg, dict) or not isinstance(cfg.get("name"), str) or not _number(cfg.get("diffusion_steps")):
        raise _fail(path, "'config' must be an object with 'name' (a string) and 'diffusion_steps' (a number)")
    if not isinstance(d["reference"], dict):
        raise _fail(path, "'reference' must be an object (the real motions' scores)")
    if not isinstance(runs, dict):
        raise _fail(path, "'runs' must be an object: variant name -> list of run records")
    for name, recs in runs.items():
        if not isinstance(recs, list):
            raise _fail(path, f"runs[{name!r}] must be a list of run records, got a {type(recs).__name__}")
        for i, r in enumerate(recs):
            where = f"runs[{name!r}][{i}]"
            if not isinstance(r, dict):
                raise _fail(path, f"{where} must be an object, got {r!r}")
            if r.get("status") != "ok":
                continue
            if not isinstance(r.get("seed"), int) or isinstance(r.get("seed"), bool):
                raise _fail(path, f"{where}: 'seed' must be an int, got {r.get('seed')!r}")
            snaps = r.get("snapshots")
            if not isinstance(snaps, list):
                raise _fail(path, f"{where}: 'snapshots' must be a list, got {snaps!r}")
            for j, s in enumerate(snaps):
                w = f"{where} snapshot {j}"
                if not isinstance(s, dict) or s.get("kind") not in ("steps", "seconds") or not _number(s.get("at")):
                    raise _fail(path, f"{w}: expected an object with 'kind' (steps or seconds) and 'at' (a number)")
                for k in ("step", *metrics):
                    if not _number(s.get(k)):
                        raise _fail(path, f"{w} ({s['at']:g} {s['kind']}): {k} is {json.dumps(s.get(k))}; "
                                          "expected a number")
    return d


# ----------------------------------------------------------------------------------------- statistics
def t_two_sided_p(t: float, df: int) -> float:
    """Two-sided p-value ``P(|T| >= |t|)`` of Student's t with ``df >= 1`` degrees of freedom (exact,
    the finite series for integer ``df``: Abramowitz & Stegun 26.7.3-4)."""
    if df < 1:
        raise ValueError(f"t_two_sided_p: df must be >= 1, got {df}")
    if math.isnan(t):
        return float("nan")
    if math.isinf(t):
        return 0.0
    th = math.atan(abs(t) / math.sqrt(df))
    c2, s = math.cos(th) ** 2, math.sin(th)
    if df % 2:  # odd
        a = th
        if df > 1:
            term, total = 1.0, 1.0
            for k in range(1, (df - 3) // 2 + 1):
                term *= c2 * (2 * k) / (2 * k + 1)
                total += term
            a += s * math.cos(th) * total
        a *= 2 / math.pi
    else:
        term, total = 1.0, 1.0
        for k in range(1, (df - 2) // 2 + 1):
            term *= c2 * (2 * k - 1) / (2 * k)
            total += term
        a = s * total
    return min(1.0, max(0.0, 1.0 - a))


def t_quantile(q: float, df: int) -> float:
    """The ``q`` quantile (``0.5 < q < 1``) of Student's t with ``df`` degrees of freedom (bisection
    on :func:`t_two_sided_p`; 1e-10 relative)."""
    if not 0.5 < q < 1:
        raise ValueError(f"t_quantile: q must be in (0.5, 1), got {q}")
    target = 2 * (1 - q)
    lo, hi = 0.0, 1.0
    while t_two_sided_p(hi, df) > target:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if t_two_sided_p(mid, df) > target:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-10 * hi:
            break
    return 0.5 * (lo + hi)


def holm(pvalues: Sequence[float]) -> List[float]:
    """Holm's step-down adjusted p-values (same order as given; NaN stays NaN and is not counted)."""
    idx = [i for i, p in enumerate(pvalues) if not math.isnan(p)]
    m = len(idx)
    out = [float("nan")] * len(pvalues)
    running = 0.0
    for rank, i in enumerate(sorted(idx, key=lambda i: pvalues[i])):
        running = max(running, min(1.0, (m - rank) * pvalues[i]))
        out[i] = running
    return out


# ----------------------------------------------------------------------------------------- cells
@dataclass
class PairedCell:
    """One (snapshot, metric): ``seeds`` both variants finished, their ``baseline`` and ``treatment``
    values (same order), the per-seed ``diffs`` (treatment − baseline), ``mean``, ``sd`` (ddof 1), ``half95`` (the cell's
    own 95% t half-width), ``p`` (two-sided paired t-test), and, filled by :func:`paired_cells`,
    ``primary``, ``p_holm`` (Holm over its family) and ``half_family`` (primary: the Bonferroni
    simultaneous 95% half-width; exploratory: ``half95``)."""

    snap: Snap
    metric: str
    seeds: List[int]
    baseline: List[float]
    treatment: List[float]
    diffs: List[float] = field(default_factory=list)
    mean: float = float("nan")
    sd: float = float("nan")
    half95: float = float("nan")
    p: float = float("nan")
    primary: bool = False
    p_holm: float = float("nan")
    half_family: float = float("nan")

    def __post_init__(self) -> None:
        self.diffs = [b - a for a, b in zip(self.baseline, self.treatment)]
        d = [x for x in self.diffs if math.isfinite(x)]
        n = len(d)
        if n:
            self.mean = sum(d) / n
        if n >= 2:
            sd = math.sqrt(sum((x - self.mean) ** 2 for x in d) / (n - 1))
            self.sd = sd
            self.half95 = t_quantile(0.975, n - 1) * sd / math.sqrt(n)
            self.p = 1.0 if sd == 0 and self.mean == 0 else (
                0.0 if sd == 0 else t_two_sided_p(self.mean / (sd / math.sqrt(n)), n - 1))
        self.half_family = self.half95

    @property
    def n(self) -> int:
        return sum(1 for x in self.diffs if math.isfinite(x))

    def excludes_zero(self) -> bool:
        """Whether the family-corrected decision rejects 0 (Holm-adjusted p < 0.05)."""
        return self.p_holm < 0.05


def _snapshots(run: Dict[str, Any]) -> Dict[Snap, Dict[str, Any]]:
    return {(s["kind"], float(s["at"])): s for s in run.get("snapshots", [])}


def primary_endpoints(cfg: Dict[str, Any]) -> List[Tuple[Snap, str]]:
    """The pre-registered ``(snapshot, metric)`` endpoints of a study config (``primary``), in order."""
    pre = cfg.get("primary") or {}
    snaps = [("seconds", float(a)) for a in pre.get("seconds", [])] + [("steps", float(a)) for a in pre.get("steps", [])]
    return [(s, m) for s in snaps for m in pre.get("metrics", [])]


def paired_cells(results: Dict[str, Any], pair: Tuple[str, str] = PAIR,
                 metrics: Sequence[str] = tuple(m for m, _, _ in METRICS)) -> List[PairedCell]:
    """Every (snapshot, metric) cell of ``results`` (:func:`read_results`) over the seeds both
    variants of ``pair`` finished, the primary ones first, with their family corrections."""
    runs = results["runs"]
    ok = {v: {r["seed"]: _snapshots(r) for r in runs.get(v, []) if r.get("status") == "ok"} for v in pair}
    seeds = sorted(set(ok[pair[0]]) & set(ok[pair[1]]))
    snaps = sorted({k for s in seeds for k in ok[pair[0]][s]} & {k for s in seeds for k in ok[pair[1]][s]},
                   key=lambda k: (k[0] != "seconds", k[1]))
    primary = primary_endpoints(results["config"])
    cells: List[PairedCell] = []
    for snap in snaps:
        have = [s for s in seeds if snap in ok[pair[0]][s] and snap in ok[pair[1]][s]]
        for m in metrics:
            c = PairedCell(snap, m, have, [float(ok[pair[0]][s][snap][m]) for s in have],
                           [float(ok[pair[1]][s][snap][m]) for s in have])
            c.primary = (snap, m) in primary
            cells.append(c)
    cells.sort(key=lambda c: not c.primary)  # stable: primaries first, each group in table order
    for fam in ([c for c in cells if c.primary], [c for c in cells if not c.primary]):
        for c, ph in zip(fam, holm([c.p for c in fam])):
            c.p_holm = ph
        if fam and fam[0].primary:
            m = sum(1 for c in fam if c.n >= 2)
            for c in fam:
                if c.n >= 2 and m:
                    c.half_family = t_quantile(1 - 0.025 / m, c.n - 1) * c.sd / math.sqrt(c.n)
    return cells


# ----------------------------------------------------------------------------------------- markdown
LABELS = {m: (label, d) for m, label, d in METRICS}


def snap_label(snap: Snap, clock: str = "cpu") -> str:
    """``"1200 s cpu"`` / ``"2000 steps"``."""
    return f"{snap[1]:g} s {clock}" if snap[0] == "seconds" else f"{snap[1]:g} steps"


def _mean(v: Sequence[float]) -> float:
    f = [x for x in v if math.isfinite(x)]
    return sum(f) / len(f) if f else float("nan")


def _g(v: float, spec: str) -> str:
    return "—" if not math.isfinite(v) else format(v, spec)


def _spec(metric: str) -> str:
    return {"fid": ".2f", "jitter_per_speed": ".0f", "jitter": ".0f", "speed": ".2f"}.get(metric, ".3f")


def _p(p: float) -> str:
    return "—" if math.isnan(p) else ("< 0.001" if p < 0.001 else f"{p:.3f}")


def cell_row(c: PairedCell, clock: str, pair: Tuple[str, str] = PAIR) -> str:
    """One markdown row: snapshot, metric, baseline / treatment means, the difference with its interval
    (family-corrected for a primary), the per-seed differences, p and the Holm-adjusted p."""
    label, d = LABELS.get(c.metric, (c.metric, 0))
    arrow = {-1: " ↓", 1: " ↑", 0: ""}[d]
    spec = _spec(c.metric)
    ci = (f"{c.mean:+{spec}} ± {_g(c.half_family, spec)}" if c.n >= 2 else f"{_g(c.mean, '+' + spec)} (n = {c.n})")
    per = ", ".join(_g(x, "+" + spec) for x in c.diffs)
    return (f"| {snap_label(c.snap, clock)} | {label}{arrow} | {_g(_mean(c.baseline), spec)} | "
            f"{_g(_mean(c.treatment), spec)} | {ci} | {per} | {_p(c.p)} | {_p(c.p_holm)} |")


def _unpaired(results: Dict[str, Any], pair: Tuple[str, str]) -> Optional[str]:
    """A line saying that no seed has both variants finished (and which runs have), or None."""
    done = {v: sorted(r["seed"] for r in results["runs"].get(v, []) if r.get("status") == "ok") for v in pair}
    if set(done[pair[0]]) & set(done[pair[1]]):
        return None
    return ("No seed has finished both variants yet (finished: "
            + ", ".join(f"{v} seeds {done[v]}" for v in pair) + "); the table fills in as they do.")


def _primary_line(cfg: Dict[str, Any], clock: str) -> str:
    ends = primary_endpoints(cfg)
    if not ends:
        return "No endpoint was pre-registered."
    return ("Pre-registered primary endpoints: " + "; ".join(f"{LABELS[m][0]} at {snap_label(sn, clock)}"
                                                             for sn, m in ends) + ".")


def markdown_tables(results: Dict[str, Any], pair: Tuple[str, str] = PAIR) -> List[str]:
    """The paired tables of one study (primary endpoints, then the exploratory cells) as markdown lines."""
    cfg = results["config"]
    clock = results.get("clock", cfg.get("clock", "cpu"))
    cells = paired_cells(results, pair)
    seeds = sorted({s for c in cells for s in c.seeds})
    prim = [c for c in cells if c.primary]
    expl = [c for c in cells if not c.primary]
    head = (f"| snapshot | metric | {pair[0]} | {pair[1]} | {pair[1]} − {pair[0]} | per seed | p | p (Holm) |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    out = [f"**{cfg['name']}** (T = {cfg['diffusion_steps']:g}): seeds {seeds} paired "
           f"({len(seeds)}; package {results.get('package_version', '?')}).", ""]
    waiting = _unpaired(results, pair)
    if waiting:
        return out + [_primary_line(cfg, clock) + " " + waiting, ""]
    if prim:
        out += [f"Primary endpoints (pre-registered; {len(prim)} tests): difference ± Bonferroni simultaneous 95% "
                "half-width, Holm-adjusted p.", "", *head, *(cell_row(c, clock, pair) for c in prim), ""]
    out += [(f"Exploratory cells ({len(expl)} tests): difference ± its own 95% t half-width; p (Holm): adjusted over "
             f"these {len(expl)} tests." if prim else
             f"No endpoint was pre-registered: all {len(expl)} cells are exploratory; difference ± its own 95% t "
             f"half-width, p (Holm): adjusted over the {len(expl)} tests."), "", *head]
    out += [cell_row(c, clock, pair) for c in expl]
    return out + [""]


def reference_lines(results: Dict[str, Any]) -> List[str]:
    """The real-motion reference rows of one study (what a FID is read against), as markdown lines."""
    ref = results["reference"]
    rows = []
    for key, label in (("fid_floor", "real test against a second draw of real test (the floor)"),
                       ("fid_train_matched", "real train motions with the test captions and lengths"),
                       ("fid_train_sample", "as many real train motions, drawn at random"),
                       ("fid_train_vs_eval", "every real train motion (first frames)")):
        v = ref.get(key)
        if not _number(v):
            continue
        iv = ref.get(f"{key}_interval")
        ci = f"[{iv[0]:.2f}, {iv[1]:.2f}]" if isinstance(iv, list) and len(iv) == 2 and all(map(_number, iv)) else "—"
        rows.append(f"| {label} | {v:.2f} | {ci} |")
    out = ["| FID reference | FID | 95% interval |", "| --- | ---: | ---: |", *rows, ""]
    return out


def summary_lines(results: Dict[str, Any], pair: Tuple[str, str] = PAIR) -> List[str]:
    """The compact table of one study, one row per snapshot: steps, FID and R@3 of both variants with
    the paired difference (± its family's interval: Bonferroni for a primary, the cell's 95% otherwise;
    ``*``: Holm-adjusted p < 0.05 in its family), R@1, jitter per unit speed, jitter and speed beside
    each other (a slow motion has little jitter), the real motions' values in the header."""
    cfg, ref = results["config"], results["reference"]
    clock = results.get("clock", cfg.get("clock", "cpu"))
    cells = {(c.snap, c.metric): c for c in paired_cells(results, pair)}
    snaps = sorted({c.snap for c in cells.values()}, key=lambda k: (k[0] != "seconds", k[1]))
    seeds = sorted({s for c in cells.values() for s in c.seeds})
    runs = {v: {r["seed"]: _snapshots(r) for r in results["runs"].get(v, []) if r.get("status") == "ok"} for v in pair}

    def both(snap: Snap, m: str) -> str:
        c = cells[(snap, m)]
        return f"{_g(_mean(c.baseline), _spec(m))} / {_g(_mean(c.treatment), _spec(m))}"

    def diff(snap: Snap, m: str) -> str:
        c = cells[(snap, m)]
        spec = _spec(m)
        if c.n < 2:
            return f"{_g(c.mean, '+' + spec)} (n = {c.n})"
        mark = "*" if c.excludes_zero() else ""
        return f"{c.mean:+{spec}} ± {_g(c.half_family, spec)}{mark}" + (" (primary)" if c.primary else "")

    def real(m: str) -> str:
        v = ref.get(m)
        return _g(float(v), _spec(m)) if _number(v) else "—"

    b, t = pair
    waiting = _unpaired(results, pair)
    out = [f"**{cfg['name']}** (T = {cfg['diffusion_steps']:g}; seeds {seeds}, package "
           f"{results.get('package_version', '?')}): {b} / {t}, mean over seeds; {t} − {b} paired per seed.", ""]
    if waiting:
        return out + [_primary_line(cfg, clock) + " " + waiting, ""]
    out += [
           f"| snapshot | steps | FID ↓ | FID diff. | R@3 ↑ (real {real('r_precision_top3')}) | R@3 diff. | "
           f"R@1 ↑ (real {real('r_precision_top1')}) | j/s (real {real('jitter_per_speed')}) | jitter (real "
           f"{real('jitter')}) | speed m/s (real {real('speed')}) | j/s diff. |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for snap in snaps:
        have = cells[(snap, "fid")].seeds
        steps = [(runs[b][s][snap]["step"], runs[t][s][snap]["step"]) for s in have]
        st = f"{_mean([x for x, _ in steps]):.0f} / {_mean([y for _, y in steps]):.0f}"
        out.append(f"| {snap_label(snap, clock)} | {st} | {both(snap, 'fid')} | {diff(snap, 'fid')} | "
                   f"{both(snap, 'r_precision_top3')} | {diff(snap, 'r_precision_top3')} | "
                   f"{both(snap, 'r_precision_top1')} | {both(snap, 'jitter_per_speed')} | {both(snap, 'jitter')} | "
                   f"{both(snap, 'speed')} | {diff(snap, 'jitter_per_speed')} |")
    fam = [c for c in cells.values() if not c.primary]
    sig = sum(1 for c in fam if c.excludes_zero())
    out += ["", f"Differences: ± the 95% t half-width over the {len(seeds)} paired seeds"
            + (" (primary endpoints: Bonferroni over the pre-registered family)" if any(c.primary for c in cells.values())
               else "") + f"; * Holm-adjusted p < 0.05 in its family. {_primary_line(cfg, clock)} Exploratory family: "
            f"{len(fam)} tests (the metrics {', '.join(m for m, _, _ in METRICS)} at every snapshot"
            + (", less the primaries" if len(fam) < len(cells) else "") + f"), {sig} below 0.05 after Holm.", ""]
    return out
