"""``smdm ablate``'s grids: the YAML schema (module docstring of :mod:`smdm_plugin.apps.ablate`),
loading and validating a grid (every key, type and range checked, one line naming it), the packaged
grids (``configs/ablations/``), variant selection (``--only``) and each variant's ``SparseConfig``."""
from __future__ import annotations

import inspect
import json
import math
import os
import re
from typing import Any, Dict, List, Optional, Sequence, Set

from ...core.presets import preset_dirs
from ...support.values import ConfigTypeError, Range, closest

DEFAULT_DATA = os.path.join("..", "shared", "data", "cmu-humanml3d")  # the scripts/ default (this project's data)
DEFAULTS: Dict[str, Any] = {
    "name": "ablation", "seed": 0, "steps": 200, "batch": 16, "max_frames": 196, "diffusion_steps": 100,
    "lr": 2e-4, "log_every": 1,
    "model": {"latent_dim": 128, "num_layers": 4, "num_heads": 4, "ff_size": 256, "arch": "trans_enc",
              "dropout": 0.1},
    "sparse": {"reduction": 0.8},
    "eval": {"samples": 8, "frames": 120, "keyframe_motions": None},
}
#: the grid settings every variant's result depends on (with the variant itself and its SparseConfig)
SHARED_SETTINGS = ("seed", "steps", "batch", "max_frames", "diffusion_steps", "lr", "model", "eval")


class AblateConfigError(ValueError):
    """The grid YAML is malformed (unknown key, wrong type or range, clashing names)."""


class AblateConfigTypeError(AblateConfigError, ConfigTypeError):
    """A value of the wrong type in the grid YAML."""


# ----------------------------------------------------------------------------------------- config
ABLATIONS_DIR = os.path.join(preset_dirs()[0], "ablations")


def packaged_grids() -> List[str]:
    return sorted(f[:-5] for f in os.listdir(ABLATIONS_DIR) if f.endswith(".yaml"))


def config_path(name_or_path: str) -> str:
    """A grid's YAML file: a path, or the name of a packaged grid (``table1``, ``defaults``,
    ``quick``: ``configs/ablations/<name>.yaml``)."""
    if os.path.isfile(name_or_path):
        return name_or_path
    packaged = os.path.join(ABLATIONS_DIR, os.path.basename(name_or_path))
    for cand in (packaged, packaged + ".yaml"):
        if os.path.isfile(cand) and os.path.dirname(name_or_path) in ("", ABLATIONS_DIR):
            return cand
    grids = packaged_grids()
    hint = closest(os.path.basename(name_or_path).removesuffix(".yaml"), grids)
    raise FileNotFoundError(f"--config {name_or_path!r} is neither a file nor a packaged grid "
                            f"({', '.join(grids)}){hint}")


def load_config(path: str) -> Dict[str, Any]:
    """The resolved grid of a YAML file (or packaged grid name); errors name the file."""
    import yaml

    p = config_path(path)
    try:
        with open(p, encoding="utf-8-sig") as f:
            cfg = yaml.safe_load(f)
    except yaml.YAMLError as e:
        raise AblateConfigError(f"{p}: not valid YAML: {' '.join(str(e).split())}") from None
    except OSError as e:
        raise AblateConfigError(f"{p}: cannot read it: {e.strerror}") from None
    try:
        return resolve(cfg if cfg is not None else {})
    except ValueError as e:
        raise type(e)(f"{p}: {e}") from None


def _model_keys() -> List[str]:
    from ...reference.backbone import TinyMDM

    fixed = {"self", "njoints", "nfeats", "cond_mode", "text_encoder"}
    return [k for k in inspect.signature(TinyMDM.__init__).parameters if k not in fixed]


def _check(where: str, v: Any, kind: type, rng: Range = Range(), optional: bool = False) -> None:
    """Raise :class:`AblateConfigError` unless ``v`` is a ``kind`` in ``rng`` (None if ``optional``)."""
    if v is None and optional:
        return
    if kind is float:
        ok_type = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    else:
        ok_type = isinstance(v, kind) and not (kind is int and isinstance(v, bool))
    what = {int: rng.describe(True), float: "a finite " + rng.describe(False)[2:], str: "a non-empty string",
            bool: "true or false", dict: "a mapping", list: "a list"}[kind]
    if not ok_type or (kind in (int, float) and v not in rng) or (kind is str and not v.strip()):
        raise (AblateConfigError if ok_type else AblateConfigTypeError)(f"{where}={v!r}: expected {'null or ' if optional else ''}{what}")


def _check_keys(where: str, d: Dict[str, Any], known: Sequence[str]) -> None:
    for k in d:
        if k not in known:
            raise AblateConfigError(f"{where}: unknown key {k!r}{closest(str(k), known)} (known: {', '.join(known)})")


def over_defaults(cfg: Any, defaults: Dict[str, Any], what: str, expected: str) -> Dict[str, Any]:
    """A grid's mapping ``cfg`` laid over a copy of ``defaults`` (mapping sections one level deep);
    only ``defaults``' keys, ``variants`` and ``data`` are known."""
    if not isinstance(cfg, dict):
        raise AblateConfigError(f"expected a mapping ({expected}), got {type(cfg).__name__}")
    _check_keys(what, cfg, [*defaults, "variants", "data"])
    out = json.loads(json.dumps(defaults))
    for k, v in cfg.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = v
    return out


def resolve(cfg: Dict[str, Any]) -> Dict[str, Any]:
    """``cfg`` over :data:`DEFAULTS` (one level deep for the mapping sections), validated: known
    keys only, types and ranges, every variant named, names and their folder names unique.
    Variants' ``sparse`` values are checked when the variant runs (an invalid one fails alone)."""
    out = over_defaults(cfg, DEFAULTS, "ablate config", "name, seed, steps, ..., variants")
    _check("name", out["name"], str)
    for k, lo in (("seed", 0), ("steps", 1), ("batch", 1), ("max_frames", 2), ("diffusion_steps", 1), ("log_every", 1)):
        _check(k, out[k], int, Range(lo))
    _check("lr", out["lr"], float, Range(0.0, lo_open=True))
    _check("data", out.get("data"), str, optional=True)
    for section in ("model", "sparse", "eval"):
        _check(section, out[section], dict)
    _check_keys("model", out["model"], _model_keys())
    _check_keys("eval", out["eval"], list(DEFAULTS["eval"]))
    _check("eval.samples", out["eval"]["samples"], int, Range(1))
    _check("eval.frames", out["eval"]["frames"], int, Range(2))
    _check("eval.keyframe_motions", out["eval"]["keyframe_motions"], int, Range(1), optional=True)
    variants = out.get("variants")
    if not variants:
        raise AblateConfigError("the config lists no variants")
    _check("variants", variants, list)
    check_variants(variants)
    return out


def check_variants(variants: List[Any]) -> None:
    """Every variant of a grid or study (``{name, dense, sparse}``) well formed: a mapping of known keys,
    a name, ``dense`` a bool, ``sparse`` a mapping (its values are checked when the variant runs), not
    both ``dense: true`` and sparse settings (they cannot apply: refused, never dropped), names and
    their folder names unique. Raises :class:`AblateConfigError` naming the variant."""
    seen: Dict[str, str] = {}
    for i, v in enumerate(variants):
        if not isinstance(v, dict):
            raise AblateConfigTypeError(f"variants[{i}]={v!r}: expected a mapping with a name")
        _check_keys(f"variants[{i}]", v, ["name", "dense", "sparse"])
        if not isinstance(v.get("name"), str) or not v["name"].strip():
            raise AblateConfigError(f"variants[{i}]: every variant needs a unique name, got {v.get('name')!r}")
        _check(f"variants[{i}].dense", v.get("dense", False), bool)
        _check(f"variants[{i}].sparse", v.get("sparse") or {}, dict)
        if v.get("dense") and v.get("sparse"):
            raise AblateConfigError(f"variants[{i}] ({v['name']!r}): sparse settings {sorted(v['sparse'])} do not "
                                    "apply to a dense variant (dense: true); drop one of them")
        s = slug(v["name"])
        if s in seen:
            same = "the same name" if seen[s] == v["name"] else f"the same folder name {s!r}"
            raise AblateConfigError(f"variants {seen[s]!r} and {v['name']!r} have {same}; every variant needs a "
                                    "unique name (and folder name: lower case, runs of other characters as '-')")
        seen[s] = v["name"]


def slug(name: str) -> str:
    """The folder name of a variant: lower case, runs of anything but ``[a-z0-9]`` as ``-``."""
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "variant"


def sparse_config(cfg: Dict[str, Any], variant: Dict[str, Any]):
    from ...core.config import SparseConfig

    if variant.get("dense"):
        return None
    d = dict(cfg.get("sparse") or {})
    d.update(variant.get("sparse") or {})
    d.setdefault("diffusion_steps", int(cfg["diffusion_steps"]))  # what runs (config.json records it)
    return SparseConfig.from_dict(d)


def select_variants(cfg: Dict[str, Any], only: Optional[Sequence[str]]) -> Set[str]:
    """The names of the variants ``only`` picks (names or folder names; all when None). An unknown
    entry is a ``ValueError`` listing the known names."""
    names = [v["name"] for v in cfg["variants"]]
    if not only:
        return set(names)
    by_slug = {slug(n): n for n in names}
    picked, unknown = set(), []
    for o in only:
        hit = o if o in names else by_slug.get(o) or by_slug.get(slug(o))
        if hit is None:
            unknown.append(o)
        else:
            picked.add(hit)
    if unknown:
        raise ValueError(f"unknown variant(s) {', '.join(map(repr, unknown))}"
                         f"{closest(unknown[0], names)}; known: {', '.join(map(repr, names))}")
    return picked
