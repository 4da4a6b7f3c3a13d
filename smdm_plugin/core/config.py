"""`SparseConfig`: every knob of the sparse keyframe method in one validated dataclass.

The config travels with a checkpoint (``sparse_config.json`` beside the weights, and the
``sparse_*`` keys of MDM's ``args.json``) so that sampling and evaluation re-create the
sparse model without extra flags.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Sequence, Tuple

CONFIG_VERSION = 1
CONFIG_FILENAME = "sparse_config.json"
#: name of the persistent buffer that marks a state dict as sparse (its value: the config version)
MARKER = "smdm_sparse_version"

SELECTORS = ("vw", "uniform", "random", "mdo")
FEATURES = ("auto", "humanml3d", "kit", "raw")
BACKENDS = ("auto", "compact", "varlen", "masked")


@dataclass
class SparseConfig:
    """All options of sparse keyframe mode.

    Units: ``reduction`` and ``gamma`` are fractions; ``frame_index_scale`` is metres per frame
    (the frame index is appended to joint positions in metres); ``mask_noise`` is the largest
    number of keyframes added or dropped per sample, as a fraction of that sample's keyframe count.
    """

    enabled: bool = True
    # --- keyframe selection -------------------------------------------------------------
    reduction: float = 0.8                 # fraction of frames dropped, in [0, 1)
    selector: str = "vw"                   # vw | uniform | random | mdo
    feature: str = "auto"                  # auto (by D: 263/251/other) | humanml3d | kit | raw
    frame_index_scale: float = 0.1         # metres per frame appended as the extra VW dimension
    mask_noise: float = 0.1                # training: up to this fraction of K added/dropped
    # --- sampling schedule ---------------------------------------------------------------
    gamma: float = 0.1                     # re-select by VW on x_t when t <= gamma * T
    dynamic_update: Optional[bool] = None  # None: on iff diffusion_steps >= 100 and no DiP prefix
    diffusion_steps: int = 50              # T; overwritten from the diffusion when attached
    prefix_frames: int = 0                 # leading frames kept dense (DiP context)
    # --- model ---------------------------------------------------------------------------
    interpolate: bool = True               # False: loss on keyframes only (ablation)
    lipschitz: bool = True                 # Lipschitz sine MLPs for input/output layers
    lipschitz_lambda: float = 1e-6         # weight of prod softplus(c_i) in the loss
    lipschitz_hidden: Optional[int] = None  # hidden width (None: the model's latent dim)
    lipschitz_layers: int = 2              # linear layers per Lipschitz MLP (>= 1)
    sine_w0: float = 1.0                   # sine activation frequency
    fsq: bool = False                      # quantise attention keys with FSQ
    fsq_levels: Tuple[int, ...] = (8, 8, 8, 5, 5, 5)
    attention_backend: str = "auto"        # auto | compact | varlen | masked
    # --- text conditioning (sMDM-stella) ------------------------------------------------------
    text_encoder: Optional[str] = None     # None: the model's own (CLIP / DistilBERT); else a
                                           # transformers hub id or local path (frozen, pooled)
    version: int = CONFIG_VERSION

    def __post_init__(self) -> None:
        if isinstance(self.fsq_levels, list):
            self.fsq_levels = tuple(int(v) for v in self.fsq_levels)
        self.validate()

    # ------------------------------------------------------------------ validation
    def validate(self) -> "SparseConfig":
        def bad(name: str, expected: str) -> None:
            raise ValueError(f"SparseConfig.{name}={getattr(self, name)!r}: expected {expected}")

        if not isinstance(self.reduction, (int, float)) or not 0.0 <= float(self.reduction) < 1.0:
            bad("reduction", "a float in [0, 1) (fraction of frames dropped)")
        if self.selector not in SELECTORS:
            bad("selector", f"one of {SELECTORS}")
        if self.feature not in FEATURES:
            bad("feature", f"one of {FEATURES}")
        if not self.frame_index_scale >= 0.0:
            bad("frame_index_scale", "a float >= 0 (metres per frame)")
        if not 0.0 <= self.mask_noise <= 1.0:
            bad("mask_noise", "a float in [0, 1] (fraction of keyframes added/dropped)")
        if not 0.0 <= self.gamma <= 1.0:
            bad("gamma", "a float in [0, 1]")
        if int(self.diffusion_steps) < 1:
            bad("diffusion_steps", "an int >= 1")
        if int(self.prefix_frames) < 0:
            bad("prefix_frames", "an int >= 0")
        if not self.lipschitz_lambda >= 0.0:
            bad("lipschitz_lambda", "a float >= 0")
        if self.lipschitz_hidden is not None and int(self.lipschitz_hidden) < 1:
            bad("lipschitz_hidden", "None or an int >= 1")
        if int(self.lipschitz_layers) < 1:
            bad("lipschitz_layers", "an int >= 1")
        if not self.sine_w0 > 0.0:
            bad("sine_w0", "a float > 0")
        if len(self.fsq_levels) < 1 or any(int(v) < 2 for v in self.fsq_levels):
            bad("fsq_levels", "a non-empty sequence of ints >= 2")
        if self.attention_backend not in BACKENDS:
            bad("attention_backend", f"one of {BACKENDS}")
        if int(self.version) > CONFIG_VERSION:
            bad("version", f"<= {CONFIG_VERSION} (config written by a newer smdm-plugin)")
        return self

    @property
    def dynamic(self) -> bool:
        """Whether sampling re-selects keyframes by VW on x_t in the last ``round(gamma*T)`` steps
        (``dynamic_update`` resolved). None (auto) follows the paper's Table 2: on when
        ``diffusion_steps >= 100`` (where it helps), off at 50 and 10 steps (neutral to worse) and
        for prefix completion (DiP)."""
        if self.dynamic_update is not None:
            return bool(self.dynamic_update)
        return int(self.diffusion_steps) >= 100 and int(self.prefix_frames) == 0

    def replace(self, **changes: Any) -> "SparseConfig":
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> Dict[str, Any]:
        d = dataclasses.asdict(self)
        d["fsq_levels"] = list(self.fsq_levels)
        return d

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "SparseConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"SparseConfig: unknown option(s) {unknown}; known: {sorted(names)}")
        return cls(**d)

    def to_json(self, path: Optional[str] = None) -> str:
        text = json.dumps(self.to_dict(), indent=2, sort_keys=True)
        if path is not None:
            with open(path, "w") as f:
                f.write(text + "\n")
        return text

    @classmethod
    def from_json(cls, text_or_path: str) -> "SparseConfig":
        if os.path.exists(text_or_path):
            with open(text_or_path) as f:
                text_or_path = f.read()
        return cls.from_dict(json.loads(text_or_path))

    def to_yaml(self, path: Optional[str] = None) -> str:
        import yaml

        text = yaml.safe_dump(self.to_dict(), sort_keys=True)
        if path is not None:
            with open(path, "w") as f:
                f.write(text)
        return text

    @classmethod
    def from_yaml(cls, text_or_path: str) -> "SparseConfig":
        import yaml

        if os.path.exists(text_or_path):
            with open(text_or_path) as f:
                text_or_path = f.read()
        data = yaml.safe_load(text_or_path) or {}
        data = data.get("sparse", data)  # allow a top-level `sparse:` section
        return cls.from_dict(data)

    @classmethod
    def load(cls, path: str) -> "SparseConfig":
        """From a ``.json`` / ``.yaml`` file, or a directory holding ``sparse_config.json``."""
        if os.path.isdir(path):
            path = os.path.join(path, CONFIG_FILENAME)
        if path.endswith((".yaml", ".yml")):
            return cls.from_yaml(path)
        return cls.from_json(path)

    def save(self, directory_or_path: str) -> str:
        path = directory_or_path
        if os.path.isdir(path):
            path = os.path.join(path, CONFIG_FILENAME)
        self.to_json(path)
        return path

    # ------------------------------------------------------------------ argparse
    @classmethod
    def add_argparse_args(cls, parser: argparse.ArgumentParser, group_title: Optional[str] = None
                          ) -> argparse.ArgumentParser:
        """Add ``--sparse`` and ``--sparse_<field>`` options to an existing parser (or to one
        of its groups when it is an ``argparse._ArgumentGroup``). Returns what it added to."""
        target = parser.add_argument_group(group_title) if group_title else parser
        defaults = cls.__new__(cls)  # field defaults without validation side effects
        for f in dataclasses.fields(cls):
            val = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore
            setattr(defaults, f.name, val)
        target.add_argument("--sparse", action="store_true",
                            help="Train/sample in sparse keyframe mode (sMDM).")
        for f in dataclasses.fields(cls):
            if f.name in ("enabled", "version"):
                continue
            default = getattr(defaults, f.name)
            flag = f"--sparse_{f.name}"
            if isinstance(default, bool) or f.name == "dynamic_update":
                target.add_argument(flag, type=_str2bool, default=default, metavar="BOOL",
                                    help=f"sparse: {f.name} (default {default})")
            elif isinstance(default, tuple):
                target.add_argument(flag, type=int, nargs="+", default=list(default),
                                    help=f"sparse: {f.name} (default {list(default)})")
            elif f.name == "lipschitz_hidden":
                target.add_argument(flag, type=int, default=None, help="sparse: lipschitz_hidden")
            elif f.name == "text_encoder":
                target.add_argument(flag, type=str, default=None, metavar="ID_OR_PATH",
                                    help="sparse: text encoder (transformers hub id or local path) in place "
                                         "of the model's CLIP/DistilBERT (sMDM-stella)")
            else:
                kw: Dict[str, Any] = {"type": type(default), "default": default}
                if f.name == "selector":
                    kw["choices"] = SELECTORS
                elif f.name == "feature":
                    kw["choices"] = FEATURES
                elif f.name == "attention_backend":
                    kw["choices"] = BACKENDS
                target.add_argument(flag, help=f"sparse: {f.name} (default {default})", **kw)
        return parser

    @classmethod
    def from_args(cls, args: Any) -> "SparseConfig":
        """From a parsed namespace (or dict) carrying ``sparse`` and ``sparse_<field>`` keys."""
        d = vars(args) if not isinstance(args, dict) else args
        kw: Dict[str, Any] = {"enabled": bool(d.get("sparse", False))}
        for f in dataclasses.fields(cls):
            key = f"sparse_{f.name}"
            if key in d and d[key] is not None and f.name not in ("enabled", "version"):
                kw[f.name] = d[key]
            elif f.name in ("lipschitz_hidden", "dynamic_update", "text_encoder") and key in d:
                kw[f.name] = d[key]
        if "sparse_version" in d:
            kw["version"] = d["sparse_version"]
        return cls(**kw)

    def to_args_dict(self) -> Dict[str, Any]:
        """``sparse``/``sparse_<field>`` keys, as they appear in MDM's ``args.json``."""
        out: Dict[str, Any] = {"sparse": self.enabled}
        for k, v in self.to_dict().items():
            if k != "enabled":
                out[f"sparse_{k}"] = v
        return out


def _str2bool(v: str) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "y", "on"):
        return True
    if s in ("0", "false", "no", "n", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean (true/false), got {v!r}")


def preset_dirs() -> list:
    """Where presets are looked up: the package's own ``smdm_plugin/configs/``."""
    here = os.path.dirname(os.path.abspath(__file__))
    return [os.path.join(os.path.dirname(here), "configs")]


def load_preset(name: str) -> SparseConfig:
    """A preset from ``configs/`` (``smdm_humanml``, ``sdip``, ``smotiondiffuse``) or any
    YAML/JSON path."""
    if os.path.exists(name):
        return SparseConfig.load(name)
    fname = name if name.endswith((".yaml", ".yml")) else f"{name}.yaml"
    for d in preset_dirs():
        if os.path.exists(os.path.join(d, fname)):
            return SparseConfig.from_yaml(os.path.join(d, fname))
    raise ValueError(f"load_preset: unknown preset {name!r}; looked in {preset_dirs()}")
