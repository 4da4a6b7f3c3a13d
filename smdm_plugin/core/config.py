"""`SparseConfig`: every knob of the sparse keyframe method in one validated dataclass."""
from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..support.argtypes import float_range, int_range, non_empty, optional, str2bool
from ..support.config_files import PathLike, config_path, dump, read_mapping
from .registry import Choices
from .scalars import as_float, is_bool, is_int, scalar
from ..support.values import ConfigTypeError, Range, closest

CONFIG_VERSION = 1
#: name of the persistent buffer that marks a state dict as sparse (its value: the config version)
MARKER = "smdm_sparse_version"
FEATURES = ("auto", "humanml3d", "kit", "raw")
#: the run options that share the ``sparse_`` prefix of :meth:`SparseConfig.from_args` but are no config
#: field (the upstream integrations' ``--sparse_compile``, ``--sparse_preset``, ``--sparse_init_from``, and
#: what a run records beside them in ``args.json``): any other unknown ``sparse_`` key is an error
RUN_OPTIONS = ("sparse_compile", "sparse_compile_applied", "sparse_preset", "sparse_init_from", "sparse_init_origin")


def _selector_names() -> Tuple[str, ...]:
    from .selection import SELECTORS   # (torch) loaded when the choices are first read

    return SELECTORS.names()


def _backend_names() -> Tuple[str, ...]:
    from .attention_backends import BACKENDS   # (torch) loaded when the choices are first read

    return BACKENDS.names()


#: live choices of the core registries: an entry registered later is a valid value at once
SELECTORS = Choices(_selector_names)
BACKENDS = Choices(_backend_names, ("auto",))
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

    def argparse_type(self) -> Callable[[str], Any]:
        """The argparse ``type`` of the field's ``--sparse_<field>`` option (range-checked;
        ``none`` / ``auto`` give None to an optional field)."""
        if self.kind is bool:
            parse: Callable[[str], Any] = str2bool
        elif self.kind in (int, tuple):
            parse = int_range(*(None if b is None else int(b) for b in (self.range.lo, self.range.hi)))
        elif self.kind is float:
            r = self.range
            parse = float_range(r.lo, r.hi, lo_open=r.lo_open, hi_open=r.hi_open)
        else:
            parse = non_empty
        return optional(parse) if self.optional else parse


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

    def __new__(cls, *args: Any, **kwargs: Any) -> "SparseConfig":
        """An unknown keyword is a TypeError naming the closest field (``SparseConfig(redution=0.8)``
        -> "... did you mean 'reduction'?"), as :meth:`from_dict` does; checked before the
        dataclass's ``__init__`` sees it."""
        names = [f.name for f in dataclasses.fields(cls)]
        for k in kwargs:
            if k not in names:
                raise TypeError(f"SparseConfig: unknown option {k!r}{closest(k, names)} (known: {', '.join(names)})")
        return super().__new__(cls)

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
        if type(D) is not int and not is_int(D) or int(D) < 1:      # (an int first: called at every step)
            raise ConfigTypeError(f"SparseConfig.feature_kind: D must be a positive int (features per frame), "
                                  f"got {D!r}")
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
        if not isinstance(other, SparseConfig):
            raise TypeError(f"SparseConfig.differences: expected a SparseConfig, got {type(other).__name__}")
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
        return dump(self.to_dict(), "json", path)

    def to_yaml(self, path: Optional[PathLike] = None) -> str:
        """The config as YAML text; also written to ``path`` (atomically, replacing it) if given."""
        return dump(self.to_dict(), "yaml", path)

    @classmethod
    def from_json(cls, text_or_path: PathLike) -> "SparseConfig":
        """From JSON text or a ``.json`` file (see :meth:`load` for the ``sparse`` section)."""
        return cls._from_source(text_or_path, "json")

    @classmethod
    def from_yaml(cls, text_or_path: PathLike) -> "SparseConfig":
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
        path = config_path(path)
        return cls._from_source(path, "json" if path.endswith(".json") else "yaml", is_path=True)

    @classmethod
    def _from_source(cls, src: PathLike, fmt: str, is_path: bool = False) -> "SparseConfig":
        return cls.from_dict(*read_mapping(src, fmt, is_path, [f.name for f in dataclasses.fields(cls)]))

    def save(self, directory_or_path: PathLike) -> str:
        """Write ``sparse_config.json`` into a directory, or to the given file path, atomically
        (replacing an existing file; :func:`smdm_plugin.save_sparse_config` refuses to). Returns
        the path."""
        path = config_path(directory_or_path)
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
            kw: Dict[str, Any] = {"default": default, "type": spec.argparse_type(),
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
        ``sparse_<field>`` keys; keys without the prefix are ignored, an unknown ``sparse_`` key (a
        misspelt field, never dropped silently; :data:`RUN_OPTIONS` aside) is a ``ValueError``."""
        if isinstance(args, Mapping):
            d = args
        elif isinstance(args, argparse.Namespace) or hasattr(args, "__dict__"):
            d = vars(args)
        else:
            raise ConfigTypeError(f"SparseConfig.from_args: expected an argparse namespace or a mapping, "
                                  f"got {type(args).__name__}")
        keys = [f"sparse_{f.name}" for f in dataclasses.fields(cls) if f.name != "enabled"]
        unknown = [k for k in d if isinstance(k, str) and k.startswith("sparse_") and k not in keys
                   and k not in RUN_OPTIONS]
        if unknown:
            raise ValueError(f"SparseConfig: unknown option {unknown[0]!r}{closest(unknown[0], keys)}")
        enabled = d.get("sparse", False)
        if enabled is None:
            enabled = False
        if not is_bool(enabled):
            raise ConfigTypeError(f"SparseConfig: sparse must be true or false, got {enabled!r}")
        kw: Dict[str, Any] = {"enabled": enabled}
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
        wrong = [e for e in v if not is_int(e)]
        if wrong:
            raise bad(ConfigTypeError, of=wrong[0], hint=f" element {wrong[0]!r}")
        if not all(e in spec.range for e in v):
            raise bad()
        return tuple(int(e) for e in v)
    if spec.kind is int:
        if not is_int(v):
            raise bad(ConfigTypeError)
        if v not in spec.range:
            raise bad()
        return int(v)
    # float
    x = as_float(v)
    if x is None:
        hint = ""
        if isinstance(v, str):
            try:
                float(v)
                hint = " (a number read as text: YAML reads 1e-1 as a string; write 1.0e-1 or 0.1)"
            except ValueError:
                pass
        raise bad(ConfigTypeError, hint=hint)
    if not math.isfinite(x) or x not in spec.range:
        raise bad()
    return x


def _located(e: Exception, source: Optional[str]) -> Exception:
    """``e`` with ``source: `` in front of its message (same class)."""
    return type(e)(f"{source}: {e}") if source else e


