"""`SparseConfig`: every knob of the sparse keyframe method in one validated dataclass.

The config travels with a checkpoint (``sparse_config.json`` beside the weights, and the
``sparse_*`` keys of MDM's ``args.json``) so that sampling and evaluation re-create the
sparse model without extra flags.

Every field is type-checked (a bool is a ``bool``, not ``"no"``; an int is an ``int``, not ``8.7``
or ``True``; floats are finite) and range-checked, in Python, in files and on the command line
(``--sparse_<field>``, range-checked by argparse). Unknown keys are errors that suggest the
closest valid name; file errors name the file.
"""
from __future__ import annotations

import argparse
import dataclasses
import difflib
import functools
import importlib
import json
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from .atomic import atomic_write_text
from .scalars import as_float, is_bool, is_int, scalar
from .registry import Choices

CONFIG_VERSION = 1
CONFIG_FILENAME = "sparse_config.json"
#: name of the persistent buffer that marks a state dict as sparse (its value: the config version)
MARKER = "smdm_sparse_version"
FEATURES = ("auto", "humanml3d", "kit", "raw")


def _registered(module: str, registry: str, *extra: str) -> Choices:
    """Live choices of a core registry (``selection.SELECTORS``, ``attention_backends.BACKENDS``;
    its module imported on first read): an entry registered later is a valid value at once."""
    return Choices(lambda: getattr(importlib.import_module(module), registry).names(), extra)


SELECTORS = _registered("smdm_plugin.core.selection", "SELECTORS")
BACKENDS = _registered("smdm_plugin.core.attention_backends", "BACKENDS", "auto")
INTERPOLATIONS = ("linear", "cubic")
#: ``SparseConfig.sample_interpolation``: ``auto`` resolves by the feature kind (:meth:`SparseConfig.sample_fill`)
SAMPLE_FILLS = ("auto",) + INTERPOLATIONS
#: the feature kind of ``feature="auto"`` by the number of features D (others: raw)
FEATURE_KINDS_BY_DIM = {263: "humanml3d", 251: "kit"}
#: ``sample_interpolation="auto"``: the fill measured best per feature kind (docs/defaults.md, "Smooth
#: sparse sampling"): HumanML3D / KIT features (root velocities, integrated into positions) are already
#: as smooth as real motion with the paper's linear fill and over-smoothed by the C¹ fill; raw joint
#: positions are 2-3x as jerky as real motion with the linear fill and as smooth as it with the C¹ fill
AUTO_SAMPLE_FILL = {"humanml3d": "linear", "kit": "linear", "raw": "cubic"}

PathLike = Union[str, "os.PathLike[str]"]


class ConfigTypeError(TypeError, ValueError):
    """A config value of the wrong type (e.g. ``lipschitz="no"``). A ``TypeError`` that callers
    catching ``ValueError`` for bad configs also catch."""


# ----------------------------------------------------------------------------------- ranges
@dataclass(frozen=True)
class Range:
    """A numeric interval: ``[lo, hi]``, open at an end when ``lo_open`` / ``hi_open``; a bound of
    None is unbounded."""

    lo: Optional[float] = None
    hi: Optional[float] = None
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def describe(self, integer: bool) -> str:
        """``"an integer >= 1"``, ``"a number in [0, 1)"``..."""
        name = "an integer" if integer else "a number"
        lo, hi = (None if b is None else format(b, "g") for b in (self.lo, self.hi))
        if lo is not None and self.lo == self.hi and not (self.lo_open or self.hi_open):
            return f"{name} equal to {lo}"
        if lo is not None and hi is not None:
            return f"{name} in {'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"
        if lo is not None:
            return f"{name} {'>' if self.lo_open else '>='} {lo}"
        if hi is not None:
            return f"{name} {'<' if self.hi_open else '<='} {hi}"
        return name


def int_range(lo: Optional[int] = None, hi: Optional[int] = None) -> Callable[[str], int]:
    """argparse ``type``: an int in ``[lo, hi]`` (either bound may be None); a bad value is an
    argparse error naming the option (exit status 2)."""
    rng = Range(lo, hi)

    def parse(text: str) -> int:
        try:
            v = int(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v not in rng:
            raise argparse.ArgumentTypeError(f"must be {rng.describe(True)}, got {v}")
        return v

    parse.__name__ = "int"
    return parse


def float_range(lo: Optional[float] = None, hi: Optional[float] = None, *, lo_open: bool = False,
                hi_open: bool = False) -> Callable[[str], float]:
    """argparse ``type``: a finite float in ``[lo, hi]`` (``(lo`` / ``hi)`` when open)."""
    rng = Range(lo, hi, lo_open, hi_open)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v) or v not in rng:
            raise argparse.ArgumentTypeError(f"must be a finite {rng.describe(False)[2:]}, got {text}")
        return v

    parse.__name__ = "float"
    return parse


def str2bool(text: Union[str, bool]) -> bool:
    """argparse ``type``: true/false, yes/no, on/off, 1/0 (any case)."""
    if isinstance(text, bool):
        return text
    s = str(text).strip().lower()
    if s in ("1", "true", "yes", "y", "on"):
        return True
    if s in ("0", "false", "no", "n", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean (true/false), got {text!r}")


def closest(word: str, candidates: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest candidate to ``word``, or ``""``."""
    cands = list(candidates)
    lower = {c.lower(): c for c in cands}
    hit = difflib.get_close_matches(str(word).lower(), list(lower), n=1, cutoff=0.6)
    return f"; did you mean {lower[hit[0]]!r}?" if hit else ""


# ----------------------------------------------------------------------------------- fields
@dataclass(frozen=True)
class FieldSpec:
    """What a ``SparseConfig`` field accepts: ``kind`` (bool, int, float, str, or ``tuple`` of
    ints), a numeric ``range`` (for tuples: of each element), ``choices`` (str), ``optional``
    (None allowed), and the help text (units)."""

    kind: type
    help: str
    range: Range = Range()
    choices: Tuple[str, ...] = ()
    optional: bool = False
    note: str = ""            # appended to the range in error messages

    def expected(self) -> str:
        if self.kind is bool:
            what = "a bool (true/false)"
        elif self.choices:
            what = f"one of {self.choices}"
        elif self.kind is str:
            what = "a non-empty string"
        elif self.kind is tuple:
            what = f"a non-empty sequence of ints, each {self.range.describe(True)[len('an integer '):]}"
        else:
            what = self.range.describe(self.kind is int)
            what = what if self.kind is int else "a finite float" + what[len("a number"):]
        what = f"None or {what}" if self.optional else what
        return f"{what} ({self.note})" if self.note else what


def _field(default: Any, kind: type, help: str, **spec: Any) -> Any:
    """A ``SparseConfig`` field: its default and the :class:`FieldSpec` that checks it."""
    return dataclasses.field(default=default, metadata={"spec": FieldSpec(kind, help, **spec)})


def spec_of(f: "dataclasses.Field[Any]") -> FieldSpec:
    """The :class:`FieldSpec` of a ``SparseConfig`` field."""
    spec = f.metadata.get("spec")
    if not isinstance(spec, FieldSpec):
        raise TypeError(f"SparseConfig.{f.name}: declare the field with _field(default, kind, help, ...) so that "
                        "it is type- and range-checked and gets its --sparse_ option")
    return spec


@dataclass
class SparseConfig:
    """All options of sparse keyframe mode.

    Units: ``reduction`` and ``gamma`` are fractions; ``frame_index_scale`` is metres per frame
    (the frame index is appended to joint positions in metres); ``mask_noise`` is the largest
    number of keyframes added or dropped per sample, as a fraction of that sample's keyframe count.
    """

    enabled: bool = _field(True, bool, "sparse keyframe mode on")
    # --- keyframe selection -------------------------------------------------------------
    reduction: float = _field(0.8, float, "fraction of frames dropped", range=Range(0.0, 1.0, hi_open=True),
                              note="fraction of frames dropped")
    selector: str = _field("vw", str, "keyframe selector", choices=SELECTORS)
    feature: str = _field("auto", str, "what VW measures (auto: by D, 263 HumanML3D / 251 KIT / other raw)",
                          choices=FEATURES)
    frame_index_scale: float = _field(0.3, float, "metres per frame appended as the extra VW dimension",
                                      range=Range(0.0), note="metres per frame")
    mask_noise: float = _field(0.1, float, "training: up to this fraction of the keyframes added/dropped",
                               range=Range(0.0, 1.0), note="fraction of keyframes added/dropped")
    # --- sampling schedule ---------------------------------------------------------------
    gamma: float = _field(0.1, float, "the last round(gamma * T) sampling steps re-select keyframes by VW on x_t",
                          range=Range(0.0, 1.0))
    dynamic_update: Optional[bool] = _field(
        False, bool, "VW re-selection on x_t in the last steps of sampling (false: uniform always, smoother "
        "motion, measured; None/auto: the paper's Table 2, on iff diffusion_steps >= 100 and no DiP prefix)",
        optional=True)
    sample_interpolation: str = _field(
        "auto", str, "sampling: how the non-keyframes of the model's output are filled (linear: the paper's "
        "linear interpolation before the output layer only; cubic: then C1 Catmull-Rom through the output at "
        "the keyframes; auto: linear for HumanML3D/KIT features, cubic for raw joint positions, as measured)",
        choices=SAMPLE_FILLS)
    sample_interpolation_steps: Optional[int] = _field(
        None, int, "sampling: the last this many steps use sample_interpolation, the others linear "
        "(None: every step)", range=Range(1), optional=True)
    diffusion_steps: int = _field(50, int, "T (overwritten from the diffusion when attached)", range=Range(1))
    prefix_frames: int = _field(0, int, "leading frames kept dense (DiP context)", range=Range(0))
    # --- model ---------------------------------------------------------------------------
    interpolate: bool = _field(True, bool, "false: loss on keyframes only (ablation)")
    lipschitz: bool = _field(True, bool, "Lipschitz sine MLPs for the input/output layers")
    lipschitz_lambda: float = _field(0.0, float, "weight of prod softplus(c_i) in the loss", range=Range(0.0))
    lipschitz_hidden: Optional[int] = _field(None, int, "Lipschitz MLP hidden width (None/auto: latent dim)",
                                             range=Range(1), optional=True)
    lipschitz_layers: int = _field(2, int, "linear layers per Lipschitz MLP", range=Range(1))
    sine_w0: float = _field(1.0, float, "sine activation frequency", range=Range(0.0, lo_open=True))
    fsq: bool = _field(True, bool, "quantise attention keys with FSQ")
    fsq_levels: Tuple[int, ...] = _field((8, 8, 8, 5, 5, 5), tuple, "FSQ levels per key dimension",
                                         range=Range(2))
    attention_backend: str = _field("auto", str, "how keyframe tokens are packed", choices=BACKENDS)
    # --- text conditioning (sMDM-stella) ------------------------------------------------------
    text_encoder: Optional[str] = _field(
        None, str, "text encoder (transformers hub id or local path, frozen, pooled) in place of the "
        "model's CLIP/DistilBERT (None: the model's own)", optional=True)
    version: int = _field(CONFIG_VERSION, int, "config format version", range=Range(1, CONFIG_VERSION),
                          note="a larger one was written by a newer smdm-plugin")

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ validation
    def validate(self) -> "SparseConfig":
        """Check (and normalise: ints to float, sequences to tuple) every field; raise
        :class:`ConfigTypeError` for a wrong type, ``ValueError`` for a value out of range."""
        for f in dataclasses.fields(self):
            setattr(self, f.name, _check_field(f.name, spec_of(f), getattr(self, f.name)))
        return self

    @property
    def dynamic(self) -> bool:
        """Whether sampling re-selects keyframes by VW on x_t in the last ``round(gamma*T)`` steps
        (``dynamic_update`` resolved). The default, False, keeps the uniform mask (measured: the
        re-selection on noisy x_t doubles the jitter per unit speed, docs/defaults.md). None (auto)
        follows the paper's Table 2: on when ``diffusion_steps >= 100`` (where it helps FID), off at 50
        and 10 steps (neutral to worse) and for prefix completion (DiP)."""
        if self.dynamic_update is not None:
            return bool(self.dynamic_update)
        return int(self.diffusion_steps) >= 100 and int(self.prefix_frames) == 0

    def feature_kind(self, D: int) -> str:
        """What keyframe selection measures for motions of ``D`` features: ``feature``, or with
        ``feature="auto"`` humanml3d (D = 263), kit (D = 251), else raw."""
        return FEATURE_KINDS_BY_DIM.get(int(D), "raw") if self.feature == "auto" else self.feature

    def sample_fill(self, D: int) -> str:
        """``sample_interpolation`` resolved for motions of ``D`` features: ``linear`` or ``cubic``
        (``auto``: by :meth:`feature_kind`, :data:`AUTO_SAMPLE_FILL`)."""
        fill = self.sample_interpolation
        return AUTO_SAMPLE_FILL[self.feature_kind(D)] if fill == "auto" else fill

    def replace(self, **changes: Any) -> "SparseConfig":
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)

    def differences(self, other: "SparseConfig", ignore: Iterable[str] = ("version",)) -> Dict[str, Tuple[Any, Any]]:
        """``{field: (self's value, other's value)}`` for every field that differs (but ``ignore``)."""
        skip = set(ignore)
        return {f.name: (getattr(self, f.name), getattr(other, f.name)) for f in dataclasses.fields(self)
                if f.name not in skip and getattr(self, f.name) != getattr(other, f.name)}

    def summary(self) -> str:
        """The settings that shape a run, in one line (what the upstream integrations log):
        ``reduction 0.8 (vw keyframes, mask noise 0.1), FSQ keys on, Lipschitz MLPs on (λ 0), ...``."""
        onoff = {True: "on", False: "off", None: "auto"}
        parts = [f"reduction {self.reduction:g} ({self.selector} keyframes, mask noise {self.mask_noise:g})",
                 f"FSQ keys {onoff[self.fsq]}",
                 f"Lipschitz MLPs {onoff[self.lipschitz]}" + (f" (λ {self.lipschitz_lambda:g})" if self.lipschitz else ""),
                 f"fill {self.sample_interpolation}", f"dynamic update {onoff[self.dynamic_update]} (γ {self.gamma:g})",
                 f"T {self.diffusion_steps}"]
        if self.prefix_frames:
            parts.append(f"{self.prefix_frames} prefix frames dense")
        if not self.interpolate:
            parts.append("keyframe-only loss")
        if self.text_encoder:
            parts.append(f"text encoder {self.text_encoder}")
        return ", ".join(parts)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> Dict[str, Any]:
        d = dataclasses.asdict(self)
        d["fsq_levels"] = list(self.fsq_levels)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: Optional[str] = None) -> "SparseConfig":
        """From a mapping of field names; unknown names are an error suggesting the closest valid
        one. ``source`` (a file name) prefixes error messages."""
        if not isinstance(d, Mapping):
            raise _located(ConfigTypeError(f"SparseConfig: expected a mapping of options, got "
                                           f"{type(d).__name__}"), source)
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = [k for k in d if k not in names]
        if unknown:
            k = unknown[0]
            raise _located(ValueError(f"SparseConfig: unknown option {k!r}{closest(str(k), names)} "
                                      f"(known: {', '.join(names)})"), source)
        try:
            return cls(**d)
        except (TypeError, ValueError) as e:
            raise _located(e, source) from None

    def to_json(self, path: Optional[PathLike] = None) -> str:
        """The config as JSON text; also written to ``path`` (atomically, replacing it) if given."""
        text = json.dumps(self.to_dict(), indent=2, sort_keys=True)
        if path is not None:
            atomic_write_text(path, text + "\n")
        return text

    def to_yaml(self, path: Optional[PathLike] = None) -> str:
        """The config as YAML text; also written to ``path`` (atomically, replacing it) if given."""
        import yaml

        text = yaml.safe_dump(self.to_dict(), sort_keys=True)
        if path is not None:
            atomic_write_text(path, text)
        return text

    @classmethod
    def from_json(cls, text_or_path: Union[str, "os.PathLike[str]"]) -> "SparseConfig":
        """From JSON text or a ``.json`` file (see :meth:`load` for the ``sparse`` section)."""
        return cls._from_source(text_or_path, "json")

    @classmethod
    def from_yaml(cls, text_or_path: Union[str, "os.PathLike[str]"]) -> "SparseConfig":
        """From YAML text or a ``.yaml`` file (see :meth:`load` for the ``sparse`` section)."""
        return cls._from_source(text_or_path, "yaml")

    @classmethod
    def load(cls, path: PathLike) -> "SparseConfig":
        """From a ``.json`` / ``.yaml`` file, or a directory holding ``sparse_config.json``.

        When the file's mapping has a top-level ``sparse:`` section, that section is the config
        and the other top-level sections are left alone (a preset may carry e.g. ``upstream:``);
        otherwise the whole mapping is the config. A missing file is a ``FileNotFoundError``
        naming it; bad contents a ``ValueError`` naming the file.
        """
        path = os.fspath(path)
        if os.path.isdir(path):
            path = os.path.join(path, CONFIG_FILENAME)
        return cls._from_source(path, "json" if path.endswith(".json") else "yaml", is_path=True)

    @classmethod
    def _from_source(cls, src: Union[str, "os.PathLike[str]"], fmt: str, is_path: bool = False) -> "SparseConfig":
        where: Optional[str] = None
        if is_path or not isinstance(src, str) or _looks_like_path(src, fmt):
            where = os.fspath(src)
            text = _read_text(where)
        else:
            text = src
        return cls.from_dict(config_section(_parse(text, fmt, where), where), where)

    def save(self, directory_or_path: PathLike) -> str:
        """Write ``sparse_config.json`` into a directory, or to the given file path, atomically
        (replacing an existing file; :func:`smdm_plugin.save_sparse_config` refuses to). Returns
        the path."""
        path = os.fspath(directory_or_path)
        if os.path.isdir(path):
            path = os.path.join(path, CONFIG_FILENAME)
        if path.endswith((".yaml", ".yml")):
            self.to_yaml(path)
        else:
            self.to_json(path)
        return path

    # ------------------------------------------------------------------ argparse
    @classmethod
    def add_argparse_args(cls, parser: argparse.ArgumentParser, group_title: Optional[str] = None
                          ) -> argparse.ArgumentParser:
        """Add ``--sparse`` and ``--sparse_<field>`` options to an existing parser (or to one
        of its groups when it is an ``argparse._ArgumentGroup``). Every value is type- and
        range-checked by argparse (a bad one: one line naming the option, exit status 2);
        ``none``/``auto`` gives None to the optional fields. Returns what it added to."""
        target = parser.add_argument_group(group_title) if group_title else parser
        target.add_argument("--sparse", action="store_true",
                            help="Train/sample in sparse keyframe mode (sMDM).")
        for f in dataclasses.fields(cls):
            if f.name in ("enabled", "version"):
                continue
            spec = spec_of(f)
            default = list(f.default) if isinstance(f.default, tuple) else f.default
            kw: Dict[str, Any] = {"default": default, "type": _argparse_type(spec),
                                  "help": f"sparse: {spec.help} (default {default})"}
            if spec.choices:
                kw["choices"] = spec.choices
            elif spec.kind is tuple:
                kw["nargs"] = "+"
            if spec.kind is bool:
                kw["metavar"] = "BOOL|auto" if spec.optional else "BOOL"
            elif f.name == "text_encoder":
                kw["metavar"] = "ID_OR_PATH"
            target.add_argument(f"--sparse_{f.name}", **kw)
        return parser

    @classmethod
    def from_args(cls, args: Any) -> "SparseConfig":
        """From a parsed namespace (or dict, e.g. MDM's ``args.json``) carrying ``sparse`` and
        ``sparse_<field>`` keys; other keys are ignored."""
        d = vars(args) if not isinstance(args, Mapping) else args
        kw: Dict[str, Any] = {"enabled": d.get("sparse") or False}
        for f in dataclasses.fields(cls):
            key = f"sparse_{f.name}"
            if f.name == "enabled" or key not in d:
                continue
            if d[key] is not None or spec_of(f).optional:
                kw[f.name] = d[key]
        return cls(**kw)

    def to_args_dict(self) -> Dict[str, Any]:
        """``sparse``/``sparse_<field>`` keys, as they appear in MDM's ``args.json``."""
        out: Dict[str, Any] = {"sparse": self.enabled}
        for k, v in self.to_dict().items():
            if k != "enabled":
                out[f"sparse_{k}"] = v
        return out


def _init_naming_unknown(init: Callable[..., None]) -> Callable[..., None]:
    """Wrap the dataclass ``__init__``: an unknown keyword is a TypeError naming the closest field
    (``SparseConfig(redution=0.8)`` -> "... did you mean 'reduction'?"), as :meth:`SparseConfig.from_dict` does."""
    @functools.wraps(init)
    def __init__(self: "SparseConfig", *args: Any, **kwargs: Any) -> None:
        names = [f.name for f in dataclasses.fields(type(self))]
        for k in kwargs:
            if k not in names:
                raise TypeError(f"SparseConfig: unknown option {k!r}{closest(k, names)} (known: {', '.join(names)})")
        init(self, *args, **kwargs)

    return __init__


SparseConfig.__init__ = _init_naming_unknown(SparseConfig.__init__)  # type: ignore[method-assign]


# ----------------------------------------------------------------------------------- helpers
def _check_field(name: str, spec: FieldSpec, v: Any) -> Any:
    """``v`` normalised (int -> float for float fields, sequence -> tuple), or raise."""
    def bad(cls: type = ValueError, hint: str = "", of: Any = v) -> Exception:
        got = f", got {type(of).__name__}" if cls is ConfigTypeError else ""
        return cls(f"SparseConfig.{name}={v!r}: expected {spec.expected()}{got}{hint}")

    if v is None and spec.optional:
        return None
    v = scalar(v)  # numpy scalars and 0-d arrays are numbers like any other
    if spec.kind is bool:
        if not is_bool(v):
            raise bad(ConfigTypeError)
        return bool(v)
    if spec.kind is str:
        if not isinstance(v, str):
            raise bad(ConfigTypeError)
        if spec.choices and v not in spec.choices:
            raise bad(hint=closest(v, spec.choices))
        if not v.strip():
            raise bad()
        return v
    if spec.kind is tuple:
        if isinstance(v, np.ndarray) and v.ndim == 1:
            v = list(v)
        if isinstance(v, (str, bytes)) or not isinstance(v, Sequence):
            raise bad(ConfigTypeError)
        if not v:
            raise bad()
        wrong = [e for e in v if not _is_int(e)]
        if wrong:
            raise bad(ConfigTypeError, of=wrong[0], hint=f" element {wrong[0]!r}")
        if not all(e in spec.range for e in v):
            raise bad()
        return tuple(int(e) for e in v)
    if spec.kind is int:
        if not _is_int(v):
            raise bad(ConfigTypeError)
        if v not in spec.range:
            raise bad()
        return int(v)
    # float
    x = as_float(v)
    if x is None:
        raise bad(ConfigTypeError)
    if not math.isfinite(x) or x not in spec.range:
        raise bad()
    return x


def _is_int(v: Any) -> bool:
    return is_int(v)


def _argparse_type(spec: FieldSpec) -> Callable[[str], Any]:
    if spec.kind is bool:
        parse: Callable[[str], Any] = str2bool
    elif spec.kind in (int, tuple):
        parse = int_range(*(None if b is None else int(b) for b in (spec.range.lo, spec.range.hi)))
    elif spec.kind is float:
        r = spec.range
        parse = float_range(r.lo, r.hi, lo_open=r.lo_open, hi_open=r.hi_open)
    else:
        def parse(text: str) -> str:
            if not text.strip():
                raise argparse.ArgumentTypeError("expected a non-empty string")
            return text
    if not spec.optional:
        return parse
    inner = parse

    def optional(text: str) -> Any:
        return None if text.strip().lower() in ("none", "auto") else inner(text)

    optional.__name__ = getattr(inner, "__name__", "value")
    return optional


def _located(e: Exception, source: Optional[str]) -> Exception:
    """``e`` with ``source: `` in front of its message (same class)."""
    return type(e)(f"{source}: {e}") if source else e


def _looks_like_path(s: str, fmt: str) -> bool:
    if "\n" in s:
        return False
    if os.path.exists(s) or s.strip().endswith((".json", ".yaml", ".yml")):
        return True
    return fmt == "json" and not s.lstrip().startswith("{")


def _read_text(path: str) -> str:
    if not os.path.exists(path):
        raise FileNotFoundError(f"SparseConfig: no such config file: {path!r}")
    if os.path.isdir(path):
        raise IsADirectoryError(f"SparseConfig: {path!r} is a folder without {CONFIG_FILENAME}")
    with open(path, "rb") as f:
        raw = f.read()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None


def _parse(text: str, fmt: str, where: Optional[str]) -> Any:
    label = where or f"SparseConfig.from_{fmt}"
    if fmt == "json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{label}: not valid JSON: {e}") from None
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{label}: not valid YAML: {' '.join(str(e).split())}") from None


def config_section(data: Any, where: Optional[str] = None) -> Dict[str, Any]:
    """The config mapping of a parsed file: its top-level ``sparse:`` section when there is one
    (other top-level sections are then allowed), else the whole mapping (empty file: {})."""
    label = where or "SparseConfig"
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigTypeError(f"{label}: expected a mapping of SparseConfig options, got {type(data).__name__}")
    if "sparse" in data:
        section = data["sparse"]
        if section is None:
            return {}
        if not isinstance(section, Mapping):
            raise ConfigTypeError(f"{label}: the 'sparse' section must be a mapping of SparseConfig "
                                  f"options, got {type(section).__name__}")
        return dict(section)
    return dict(data)


#: fields an adapter sets from the model when it attaches (a run's command-line value may differ)
SET_WHEN_ATTACHED = ("diffusion_steps", "prefix_frames", "version")


def disagreement(saved: "SparseConfig", options: Mapping[str, Any], config_file: str, options_file: str,
                 ignore: Iterable[str] = SET_WHEN_ATTACHED) -> Optional[str]:
    """None when a run's ``sparse_*`` options (``args.json``, ``opt.txt``: ``options``, with
    ``sparse`` true) agree with its ``sparse_config.json`` (``saved``) on every field they give
    (``ignore`` aside), else a one-line message naming both files and each differing field."""
    try:
        given = SparseConfig.from_args(options)
    except ValueError as e:
        return f"{options_file}: {e}"
    keys = {f.name for f in dataclasses.fields(SparseConfig) if f"sparse_{f.name}" in options} - set(ignore)
    diff = {k: v for k, v in saved.differences(given, ignore=tuple(ignore)).items() if k in keys}
    if not diff:
        return None
    return f"{options_file} and {config_file} disagree: " + "; ".join(
        f"{k}: {os.path.basename(options_file)} {b!r}, {os.path.basename(config_file)} {a!r}" for k, (a, b) in diff.items())


def as_config(config: Any, what: str = "config") -> "SparseConfig":
    """``config`` as a validated :class:`SparseConfig`: a ``SparseConfig`` (validated again: its
    fields may have been assigned since), or a mapping of field names (converted, e.g. a parsed
    YAML/JSON ``dict``). Anything else is a :class:`ConfigTypeError` naming ``what``."""
    if isinstance(config, SparseConfig):
        return config.validate()
    if isinstance(config, Mapping):
        try:
            return SparseConfig.from_dict(config)
        except ConfigTypeError as e:
            raise ConfigTypeError(f"{what}: {e}") from None
        except ValueError as e:
            raise ValueError(f"{what}: {e}") from None
    raise ConfigTypeError(f"{what} must be a SparseConfig or a mapping of its options, got {type(config).__name__}")


def preset_dirs() -> List[str]:
    """Where presets are looked up: the project's top-level ``configs/`` (a source checkout, ``pip
    install -e .``), else where a regular install puts it (``<prefix>/share/smdm_plugin/configs``)."""
    import sys

    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    candidates = [os.path.join(os.path.dirname(package), "configs"),
                  os.path.join(sys.prefix, "share", "smdm_plugin", "configs")]
    return [d for d in candidates if os.path.isdir(d)][:1] or candidates[:1]


def preset_names() -> List[str]:
    """The packaged presets (``smdm_humanml``, ``sdip``, ``smotiondiffuse``...)."""
    return sorted(f.rsplit(".", 1)[0] for d in preset_dirs() if os.path.isdir(d) for f in os.listdir(d)
                  if f.endswith((".yaml", ".yml")))


def load_preset(name: str) -> SparseConfig:
    """A packaged preset by name or any YAML/JSON path.

    Packaged (top-level ``configs/``): ``smdm_paper`` (App. B.1: trans_dec-ready, 50 steps, FSQ
    keys, lambda 0, no dynamic update), ``sdip_paper`` (App. B.2: 10 steps, 20 past + 40 future
    frames), ``smdm_humanml`` and ``sdip`` (earlier measured variants, kept by name),
    ``smotiondiffuse``; ``preset_names()`` lists them all."""
    if os.path.exists(name):
        return SparseConfig.load(name)
    fname = name if name.endswith((".yaml", ".yml")) else f"{name}.yaml"
    for d in preset_dirs():
        if os.path.isfile(os.path.join(d, fname)):
            return SparseConfig.load(os.path.join(d, fname))
    if os.sep in name or name.endswith((".yaml", ".yml", ".json")):
        raise FileNotFoundError(f"load_preset: no such file: {name!r}")
    names = preset_names()
    raise ValueError(f"load_preset: unknown preset {name!r}{closest(name, names)} (packaged: "
                     f"{', '.join(names)}; or pass a YAML/JSON path)")
