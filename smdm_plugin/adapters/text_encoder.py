"""sMDM-stella: swap the text encoder of an MDM-family model for a frozen ``transformers`` encoder."""
from __future__ import annotations

import copy
import json
import os
import warnings
from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence, Union

import torch
import torch.nn as nn
import torch.nn.functional as F

POOLINGS = ("mean", "cls", "last", "max")
HF_EXTRA = 'pip install "smdm-plugin[hf]"'
DEFAULT_MAX_LENGTH = 512
# sentence-transformers Pooling config key -> our mode
_ST_POOLING_KEYS = {"pooling_mode_mean_tokens": "mean", "pooling_mode_cls_token": "cls",
                    "pooling_mode_lasttoken": "last", "pooling_mode_max_tokens": "max"}
_ST_UNSUPPORTED_POOLING = ("pooling_mode_mean_sqrt_len_tokens", "pooling_mode_weightedmean_tokens")


def require_transformers() -> Any:
    """``import transformers`` with a clear error naming the extra that installs it."""
    try:
        import transformers
    except ImportError as e:  # pragma: no cover - transformers is in the test extra
        raise ImportError("smdm_plugin text encoder: the text-encoder swap needs the transformers "
                          f"package; install it with {HF_EXTRA}") from e
    return transformers


# --------------------------------------------------------------------------- pooling
def pool_hidden(hidden: torch.Tensor, attention_mask: torch.Tensor, mode: str = "mean") -> torch.Tensor:
    """Pool token states ``hidden [B, L, H]`` over the tokens of ``attention_mask [B, L]`` (1 =
    token, 0 = padding; left or right padding) to ``[B, H]``: ``mean`` of the tokens, ``cls`` (the
    first position), ``last`` (the last token), ``max`` (per feature)."""
    if hidden.dim() != 3 or attention_mask.shape != hidden.shape[:2]:
        raise ValueError(f"pool_hidden: expected hidden [B, L, H] and attention_mask [B, L], got "
                         f"{tuple(hidden.shape)} and {tuple(attention_mask.shape)}")
    m = attention_mask.to(hidden.device).bool()
    if mode == "mean":
        w = m.unsqueeze(-1).to(hidden.dtype)
        return (hidden * w).sum(1) / w.sum(1).clamp_min(1.0)
    if mode == "cls":
        return hidden[:, 0]
    if mode == "last":
        pos = torch.arange(m.shape[1], device=m.device).expand_as(m)
        last = torch.where(m, pos, torch.zeros_like(pos)).amax(1)
        return hidden[torch.arange(hidden.shape[0], device=hidden.device), last]
    if mode == "max":
        return hidden.masked_fill(~m.unsqueeze(-1), torch.finfo(hidden.dtype).min).amax(1)
    raise ValueError(f"pool_hidden: mode must be one of {POOLINGS}, got {mode!r}")


# --------------------------------------------------------------------------- sentence-transformers layout
@dataclass(frozen=True)
class EncoderLayout:
    """How captions become one vector, read from the encoder's files (sentence-transformers
    layout) or the defaults: ``subfolder`` of the transformer, ``pooling`` mode, ``head`` folder
    of a ``Dense`` projection (None: none), ``normalize`` (L2), ``prompt`` prepended to each
    caption, ``max_length`` in tokens (None: from the tokenizer / model config)."""

    subfolder: str = ""
    pooling: str = "mean"
    head: Optional[str] = None
    normalize: bool = False
    prompt: str = ""
    max_length: Optional[int] = None
    sentence_transformers: bool = False


def _local_or_hub_file(name_or_path: str, relpath: str) -> Optional[str]:
    """The path of ``relpath`` inside a local folder or a hub repository (downloaded), or None
    when the file does not exist there."""
    if os.path.isdir(name_or_path):
        p = os.path.join(name_or_path, relpath)
        return p if os.path.isfile(p) else None
    from huggingface_hub import hf_hub_download
    from huggingface_hub.errors import EntryNotFoundError, LocalEntryNotFoundError

    try:
        return hf_hub_download(name_or_path, relpath)
    except LocalEntryNotFoundError:
        warnings.warn(f"smdm text encoder: could not look up {relpath} of {name_or_path!r} (offline and "
                      "not cached); assuming no sentence-transformers layout", stacklevel=3)
        return None
    except EntryNotFoundError:
        return None


def _read_json(path: Optional[str]) -> Optional[Dict[str, Any]]:
    if path is None:
        return None
    with open(path) as f:
        return json.load(f)


def read_layout(name_or_path: str, pooling: Optional[str] = None) -> EncoderLayout:
    """The :class:`EncoderLayout` of an encoder folder or hub id (``pooling`` overrides the mode)."""
    if pooling is not None and pooling not in POOLINGS:
        raise ValueError(f"text encoder: pooling must be None or one of {POOLINGS}, got {pooling!r}")
    modules = _read_json(_local_or_hub_file(name_or_path, "modules.json"))
    if not modules:
        return EncoderLayout(pooling=pooling or "mean")
    kw: Dict[str, Any] = {"sentence_transformers": True}
    for m in sorted(modules, key=lambda m: int(m.get("idx", 0))):
        kind, path = str(m.get("type", "")).rsplit(".", 1)[-1], m.get("path", "") or ""
        if kind == "Transformer":
            kw["subfolder"] = path
            cfg = _read_json(_local_or_hub_file(name_or_path, os.path.join(path, "sentence_bert_config.json")
                                                if path else "sentence_bert_config.json"))
            if cfg and cfg.get("max_seq_length"):
                kw["max_length"] = int(cfg["max_seq_length"])
        elif kind == "Pooling":
            cfg = _read_json(_local_or_hub_file(name_or_path, f"{path}/config.json")) or {}
            on = [mode for key, mode in _ST_POOLING_KEYS.items() if cfg.get(key)]
            odd = [key for key in _ST_UNSUPPORTED_POOLING if cfg.get(key)]
            if odd or len(on) > 1:
                raise ValueError(f"text encoder {name_or_path!r}: pooling {odd + on} is not supported "
                                 f"(one of {POOLINGS}); pass pooling= to choose one")
            kw["pooling"] = on[0] if on else "mean"
        elif kind == "Dense":
            if "head" in kw:
                raise ValueError(f"text encoder {name_or_path!r}: more than one Dense module is not supported")
            kw["head"] = path
        elif kind == "Normalize":
            kw["normalize"] = True
        else:
            raise ValueError(f"text encoder {name_or_path!r}: sentence-transformers module {kind!r} "
                             "is not supported (Transformer, Pooling, Dense, Normalize are)")
    st = _read_json(_local_or_hub_file(name_or_path, "config_sentence_transformers.json")) or {}
    prompt_name = st.get("default_prompt_name")
    if prompt_name:
        kw["prompt"] = str(st.get("prompts", {}).get(prompt_name, ""))
    if pooling is not None:
        kw["pooling"] = pooling
    return EncoderLayout(**kw)


_ACTIVATIONS = {"Identity": nn.Identity, "Tanh": nn.Tanh, "ReLU": nn.ReLU, "GELU": nn.GELU,
                "Sigmoid": nn.Sigmoid, "SiLU": nn.SiLU}


def load_dense_head(name_or_path: str, folder: str) -> nn.Sequential:
    """A sentence-transformers ``Dense`` module (``config.json`` + ``linear.weight/bias`` in
    ``model.safetensors`` or ``pytorch_model.bin``) as ``Sequential(Linear, activation)``."""
    cfg = _read_json(_local_or_hub_file(name_or_path, f"{folder}/config.json"))
    if cfg is None:
        raise FileNotFoundError(f"text encoder {name_or_path!r}: {folder}/config.json (Dense head) not found")
    act_name = str(cfg.get("activation_function", "torch.nn.modules.linear.Identity")).rsplit(".", 1)[-1]
    if act_name not in _ACTIVATIONS:
        raise ValueError(f"text encoder {name_or_path!r}: Dense activation {act_name!r} is not supported "
                         f"({sorted(_ACTIVATIONS)})")
    linear = nn.Linear(int(cfg["in_features"]), int(cfg["out_features"]), bias=bool(cfg.get("bias", True)))
    st = _local_or_hub_file(name_or_path, f"{folder}/model.safetensors")
    if st is not None:
        from safetensors.torch import load_file

        state = load_file(st)
    else:
        pt = _local_or_hub_file(name_or_path, f"{folder}/pytorch_model.bin")
        if pt is None:
            raise FileNotFoundError(f"text encoder {name_or_path!r}: no weights in {folder}/ "
                                    "(model.safetensors or pytorch_model.bin)")
        state = torch.load(pt, map_location="cpu", weights_only=True)
    linear.load_state_dict({k.split("linear.", 1)[-1]: v for k, v in state.items()})
    return nn.Sequential(linear, _ACTIVATIONS[act_name]())


def _hidden_size(config: Any) -> int:
    for attr in ("hidden_size", "d_model", "dim", "n_embd"):
        value = getattr(config, attr, None)
        if isinstance(value, int) and value > 0:
            return value
    raise ValueError(f"text encoder: cannot read the hidden size from {type(config).__name__} "
                     "(expected hidden_size / d_model / dim)")


def _transformers_version() -> tuple:
    version = require_transformers().__version__.split(".")
    return tuple(int("".join(c for c in v if c.isdigit()) or 0) for v in version[:2])


# --------------------------------------------------------------------------- the encoder
class HFTextEncoder(nn.Module):
    """A frozen ``transformers`` text encoder: captions -> pooled embeddings ``[B, width]`` float32.

    Args:
        name_or_path: hub id or local folder (``AutoModel`` / ``AutoTokenizer``).
        pooling: None (the encoder's sentence-transformers layout, else ``mean``) or one of
            :data:`POOLINGS`.
        trust_remote_code: run modelling code shipped with the encoder (``auto_map``), as
            ``transformers`` does; off by default (then transformers' own class is used).
        dtype: the encoder's weight dtype (None: as saved / float32); the output is float32.
        max_length: truncate captions to this many tokens (None: the layout's, the tokenizer's or
            the model's limit, at most 512).

    The ``transformers`` model and the projection head are not registered submodules: they are
    moved by ``.to()`` with the model, but do not appear in ``parameters()`` / ``state_dict()``, do
    not follow ``.train()`` and are shared (not copied) by ``copy.deepcopy`` (EMA copies).
    """

    def __init__(self, name_or_path: str, *, pooling: Optional[str] = None, trust_remote_code: bool = False,
                 dtype: Optional[torch.dtype] = None, max_length: Optional[int] = None) -> None:
        super().__init__()
        if not isinstance(name_or_path, str) or not name_or_path:
            raise TypeError(f"HFTextEncoder: name_or_path must be a non-empty str, got {name_or_path!r}")
        if max_length is not None and int(max_length) < 1:
            raise ValueError(f"HFTextEncoder: max_length must be None or an int >= 1, got {max_length}")
        transformers = require_transformers()
        layout = read_layout(name_or_path, pooling)
        kw: Dict[str, Any] = {"trust_remote_code": bool(trust_remote_code)}
        if layout.subfolder:
            kw["subfolder"] = layout.subfolder
        model_kw = dict(kw)
        if dtype is not None:
            model_kw["dtype" if _transformers_version() >= (4, 56) else "torch_dtype"] = dtype
        config = transformers.AutoConfig.from_pretrained(name_or_path, **kw)
        if getattr(config, "auto_map", None) and not trust_remote_code:
            warnings.warn(f"smdm text encoder: {name_or_path!r} ships its own modelling code (auto_map); "
                          "transformers' built-in class is used instead. Set trust_remote_code "
                          "(SMDM_TRUST_REMOTE_CODE=1 for smdm run / the MDM patch) to run the authors' code "
                          "(stella_en_1.5B_v5 is meant to run it)", stacklevel=2)
        model = transformers.AutoModel.from_pretrained(name_or_path, **model_kw)
        if getattr(model.config, "is_encoder_decoder", False) and hasattr(model, "get_encoder"):
            model = model.get_encoder()  # T5-style: the encoder stack only
        tokenizer = transformers.AutoTokenizer.from_pretrained(name_or_path, **kw)
        if tokenizer.pad_token is None:
            fallback = tokenizer.eos_token or tokenizer.unk_token
            if fallback is None:
                raise ValueError(f"HFTextEncoder: the tokenizer of {name_or_path!r} has no pad, eos or unk "
                                 "token to pad a batch of captions with")
            tokenizer.pad_token = fallback
        hidden = _hidden_size(model.config)
        head = load_dense_head(name_or_path, layout.head) if layout.head else None
        if head is not None and head[0].in_features != hidden:
            raise ValueError(f"HFTextEncoder: the Dense head of {name_or_path!r} takes {head[0].in_features} "
                             f"features but the encoder's hidden size is {hidden}")
        frozen = nn.ModuleDict({"model": model, "head": head if head is not None else nn.Identity()})
        frozen.requires_grad_(False)
        frozen.eval()
        limits = [v for v in (max_length, layout.max_length,
                              getattr(tokenizer, "model_max_length", None),
                              getattr(model.config, "max_position_embeddings", None))
                  if isinstance(v, int) and 0 < v < 10 ** 6]
        object.__setattr__(self, "_frozen", frozen)  # not a registered submodule (see the docstring)
        object.__setattr__(self, "_tokenizer", tokenizer)
        self.name_or_path = name_or_path
        self.layout = layout
        self.pooling = layout.pooling
        self.width = int(head[0].out_features) if head is not None else hidden
        self.max_length = int(max_length) if max_length is not None else min(limits + [DEFAULT_MAX_LENGTH])
        self.trust_remote_code = bool(trust_remote_code)

    # ------------------------------------------------------------------ identity, device
    @property
    def identity(self) -> str:
        """What makes two encoders give the same embedding (the text cache keys on it)."""
        lay = self.layout
        return (f"hf:{self.name_or_path}|pool={lay.pooling}|head={lay.head}|norm={lay.normalize}|"
                f"prompt={lay.prompt!r}|max_len={self.max_length}|remote={self.trust_remote_code}")

    @property
    def device(self) -> torch.device:
        return next(self._frozen.parameters()).device

    @property
    def transformer(self) -> nn.Module:
        """The frozen ``transformers`` model."""
        return self._frozen["model"]

    @property
    def tokenizer(self) -> Any:
        return self._tokenizer

    def frozen_modules(self) -> nn.Module:
        """The hidden modules (model and head), e.g. to fingerprint their weights."""
        return self._frozen

    def extra_repr(self) -> str:
        return f"{self.name_or_path!r}, width={self.width}, pooling={self.pooling!r}, head={self.layout.head!r}"

    # ------------------------------------------------------------------ nn.Module plumbing
    def _apply(self, fn, recurse: bool = True):
        super()._apply(fn, recurse)
        self._frozen._apply(fn)
        return self

    def train(self, mode: bool = True) -> "HFTextEncoder":
        """Frozen: stays in eval mode whatever the parent model does (no dropout)."""
        return super().train(False)

    def __deepcopy__(self, memo: Dict[int, Any]) -> "HFTextEncoder":
        new = self.__class__.__new__(self.__class__)
        memo[id(self)] = new
        for key, value in self.__dict__.items():
            shared = key in ("_frozen", "_tokenizer")
            object.__setattr__(new, key, value if shared else copy.deepcopy(value, memo))
        return new

    # ------------------------------------------------------------------ encoding
    def forward(self, texts: Union[str, Sequence[str]]) -> torch.Tensor:
        """Captions ``[B]`` -> pooled embeddings ``[B, width]`` (float32, no gradient)."""
        texts = [texts] if isinstance(texts, str) else list(texts)
        if not texts or not all(isinstance(t, str) for t in texts):
            raise TypeError("HFTextEncoder: texts must be a non-empty list of str, got "
                            f"{[type(t).__name__ for t in texts][:4]}")
        prompt = self.layout.prompt
        batch = self._tokenizer([prompt + t for t in texts], padding=True, truncation=True,
                                max_length=self.max_length, return_tensors="pt")
        device = self.device
        batch = {k: v.to(device) for k, v in batch.items()}
        with torch.no_grad():
            out = self._frozen["model"](**batch)
            hidden = out.last_hidden_state if hasattr(out, "last_hidden_state") else out[0]
            pooled = self._frozen["head"](pool_hidden(hidden, batch["attention_mask"], self.pooling))
            if self.layout.normalize:
                pooled = F.normalize(pooled, dim=-1)
        return pooled.float()


# --------------------------------------------------------------------------- model surgery
class EncodeText:
    """The ``encode_text`` / ``text_encoder`` callable a swapped model gets: ``texts [B]`` -> the
    model's own text-feature convention. ``style``: ``mdm`` ``[1, B, W]`` (MDM's CLIP), ``dip``
    ``([1, B, W], pad mask [B, 1] all False)`` (DiP's DistilBERT: one text token), ``flat``
    ``[B, W]`` (TinyMDM). ``source``: the encoder's id (hub id, folder or class name), what
    :func:`swapped_text_encoder` reports."""

    STYLES = ("mdm", "dip", "flat")

    def __init__(self, encoder: nn.Module, style: str, source: Optional[str] = None) -> None:
        if style not in self.STYLES:
            raise ValueError(f"EncodeText: style must be one of {self.STYLES}, got {style!r}")
        self.encoder, self.style, self.source = encoder, style, source

    def __call__(self, texts: Sequence[str]) -> Any:
        emb = self.encoder(texts)  # [B, W]
        if self.style == "flat":
            return emb
        if self.style == "mdm":
            return emb.unsqueeze(0)
        return emb.unsqueeze(0), torch.zeros(emb.shape[0], 1, dtype=torch.bool, device=emb.device)


def _text_style(model: nn.Module) -> str:
    if not isinstance(getattr(model, "embed_text", None), nn.Linear):
        raise TypeError(f"swap_text_encoder: {type(model).__name__} has no text projection embed_text "
                        "(nn.Linear); is it text-conditioned (cond_mode 'text')?")
    if hasattr(model, "encode_text") and hasattr(model, "text_encoder_type"):
        return "dip" if model.text_encoder_type == "bert" else "mdm"
    if hasattr(model, "text_encoder"):
        return "flat"
    raise TypeError(f"swap_text_encoder: {type(model).__name__} is not an MDM-family model (expected "
                    "encode_text + text_encoder_type (MDM, DiP) or text_encoder (TinyMDM))")


def _installed(model: nn.Module) -> Optional[EncodeText]:
    """The :class:`EncodeText` :func:`swap_text_encoder` installed on ``model`` (through a text
    cache, which keeps it as ``encode``), else None: the model carries no attribute of ours."""
    for attr in ("encode_text", "text_encoder"):
        fn = model.__dict__.get(attr)
        fn = fn if isinstance(fn, EncodeText) else getattr(fn, "encode", None)
        if isinstance(fn, EncodeText):
            return fn
    return None


def swapped_text_encoder(model: nn.Module) -> Optional[str]:
    """The id of the encoder :func:`swap_text_encoder` put into ``model`` (None if never swapped)."""
    fn = _installed(model)
    return None if fn is None else fn.source


def text_encoder_of(model: nn.Module) -> Optional[nn.Module]:
    """The encoder :func:`swap_text_encoder` put into ``model`` (None if never swapped)."""
    return getattr(model, "clip_model", None) if _installed(model) is not None else None


def _warn_unused(**settings: Any) -> None:
    """Warn about the settings (not at their defaults: None / False) that only build an encoder
    from a hub id / folder, given with a ready module."""
    given = [f"{k}={v!r}" for k, v in settings.items() if v not in (None, False)]
    if given:
        warnings.warn(f"swap_text_encoder: {', '.join(given)} ignored: they apply when encoder is a hub id / "
                      "folder (an HFTextEncoder is built with them); a ready module is used as it is",
                      UserWarning, stacklevel=3)


def swap_text_encoder(model: nn.Module, encoder: Union[str, nn.Module], *, pooling: Optional[str] = None,
                      trust_remote_code: bool = False, dtype: Optional[torch.dtype] = None) -> nn.Module:
    """Replace the text encoder of an MDM / DiP / TinyMDM model in place and return the model.

    Args:
        model: MDM (CLIP), DiP (DistilBERT, ``text_encoder_type='bert'``) or ``TinyMDM``.
        encoder: a hub id or local folder (an :class:`HFTextEncoder` is built with ``pooling``,
            ``trust_remote_code``, ``dtype``), or a ready module with a ``width`` attribute (a positive
            int) that maps ``texts [B]`` to ``[B, width]`` (then those three settings are ignored: a warning).

    The encoder goes to ``model.clip_model`` (the name MDM's checkpoint code already leaves out of
    saved weights), ``model.embed_text`` becomes ``nn.Linear(width, latent_dim)`` (new weights: train
    it), ``model.clip_dim = width``, and ``encode_text`` (MDM, DiP) / ``text_encoder`` (TinyMDM) the
    :class:`EncodeText` of the model's convention, which records the id
    (:func:`swapped_text_encoder`).
    """
    style = _text_style(model)
    name = encoder if isinstance(encoder, str) else getattr(encoder, "name_or_path", type(encoder).__name__)
    if isinstance(encoder, str):
        encoder = HFTextEncoder(encoder, pooling=pooling, trust_remote_code=trust_remote_code, dtype=dtype)
    elif not isinstance(encoder, nn.Module) or not hasattr(encoder, "width"):
        raise TypeError("swap_text_encoder: encoder must be a hub id / folder or an nn.Module with an int "
                        f"width, got {type(encoder).__name__}")
    else:
        _warn_unused(pooling=pooling, trust_remote_code=trust_remote_code, dtype=dtype)
    width = encoder.width
    if isinstance(width, bool) or not isinstance(width, int):
        raise TypeError(f"swap_text_encoder: encoder.width must be a positive int (its embedding size), got "
                        f"{type(width).__name__} {width!r}")
    if width < 1:
        raise ValueError(f"swap_text_encoder: encoder.width must be a positive int (its embedding size), got {width}")
    old: nn.Linear = model.embed_text
    ref = old.weight
    encoder.to(ref.device)
    proj = nn.Linear(width, old.out_features, bias=old.bias is not None).to(ref.device, ref.dtype)
    if style == "flat" and "text_encoder" in model._modules:
        del model._modules["text_encoder"]
    model.clip_model = encoder
    model.clip_dim = width
    model.embed_text = proj
    fn = EncodeText(encoder, style, name)
    if style == "flat":
        model.text_encoder = fn
    else:
        model.encode_text = fn
    return model
