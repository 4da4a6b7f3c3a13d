"""Checkpoint files: the sparse config lives beside the weights (``sparse_config.json``, and the
``sparse_*`` keys of MDM's ``args.json``); the weights are read and checked, and loading a sparse
state dict into a dense model (or the reverse) is a clear error. io knows no model family: making a
model what a saved config describes, and the one ``load_checkpoint``, are
:mod:`smdm_plugin.adapters.checkpoint`'s."""
from __future__ import annotations

import json
import os
from typing import Any, Dict, Iterable, Mapping, Optional, Tuple

import torch
import torch.nn as nn

from ..core.agreement import disagreement
from ..core.config import MARKER, SparseConfig
from ..support.config_files import CONFIG_FILENAME
from .files import OutputExistsError
from .validate import int_field, read_json_object, require_fields

BACKBONE_FILENAME = "backbone.json"
#: ``smdm train``'s settings of the run (``training.trainer``), beside its weights
TRAIN_CONFIG_FILENAME = "train_config.json"
#: what sampling a bundle needs besides the weights (``training.bundle``)
MOTION_FILENAME = "motion.json"

class CheckpointMismatchError(ValueError, RuntimeError):
    """Weights that do not fit the model they are loaded into (sparse into dense or the reverse,
    missing or unexpected keys, shapes or dtypes that differ). A ``ValueError``, as every bad input;
    also a ``RuntimeError``, what 0.10 raised (and ``torch.nn.Module.load_state_dict`` raises)."""


def _dir_of(path: str) -> str:
    return path if os.path.isdir(path) else os.path.dirname(os.path.abspath(path))


def write_sparse_config(config: SparseConfig, directory: str, overwrite: bool = False) -> str:
    """Write ``sparse_config.json`` into ``directory`` (created if needed), atomically; returns its
    path. An existing file holding the same config is left as it is (saving twice, or from every
    rank of a distributed run, is fine); one holding another config (or unreadable) is an
    :class:`~smdm_plugin.io.files.OutputExistsError` (a ``FileExistsError``) unless ``overwrite``."""
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, CONFIG_FILENAME)
    if os.path.isdir(path):
        raise OutputExistsError(f"save_sparse_config: {path!r} is a folder")
    if not overwrite and os.path.lexists(path):
        why = _how_it_differs(path, config)
        if why is None:
            return path
        raise OutputExistsError(f"save_sparse_config: {path!r} exists with {why}; pass overwrite=True "
                                "(--overwrite) to replace it")
    return config.save(path)


def _how_it_differs(path: str, config: SparseConfig) -> Optional[str]:
    """None when ``path`` holds ``config`` (its version aside), else what it holds instead."""
    try:
        saved = SparseConfig.load(path)
    except (OSError, ValueError) as e:  # ConfigTypeError is a ValueError too
        return f"contents that are not a valid config ({e})"
    diff = saved.differences(config)
    return f"another config (differs in {', '.join(diff)})" if diff else None


def find_sparse_config(checkpoint_path: str) -> Optional[SparseConfig]:
    """The config saved beside a checkpoint: ``sparse_config.json``, else ``args.json``'s
    ``sparse``/``sparse_*`` keys (MDM), else None."""
    return find_config(checkpoint_path)[0]


def find_config(checkpoint_path: str) -> Tuple[Optional[SparseConfig], Optional[str]]:
    """``(config, the file it came from)`` or ``(None, None)``; errors name the file."""
    import dataclasses

    d = _dir_of(checkpoint_path)
    p = os.path.join(d, CONFIG_FILENAME)
    args = os.path.join(d, "args.json")
    config: Optional[SparseConfig] = None
    if os.path.exists(p):
        config = SparseConfig.load(p)
        # a versioned file: every field must be there (a missing one is an error, never a default)
        require_fields(read_json_object(p), [f.name for f in dataclasses.fields(SparseConfig)], p)
    if os.path.exists(args):
        a = read_json_object(args)
        if config is not None and config.enabled and "sparse" in a and not a["sparse"]:
            raise ValueError(f"{args} and {p} disagree: {os.path.basename(args)} says the run was dense "
                             f"(sparse: {a['sparse']!r}), {CONFIG_FILENAME} holds an enabled sparse config")
        if a.get("sparse"):
            try:
                from_args = SparseConfig.from_args(a)
            except ValueError as e:  # ConfigTypeError too
                raise type(e)(f"{args}: {e}") from None
            if config is None:
                return from_args, args
            why = disagreement(config, a, p, args)  # the two files describe the same model: they must agree
            if why:
                raise ValueError(why)
    config_file = p if config is not None else None
    check_run_files(d, config, config_file)
    return (config, config_file) if config is not None else (None, None)


def _disagree(a_file: str, b_file: str, diff: Mapping[str, Tuple[Any, Any]]) -> ValueError:
    """The error of two files of one run holding different values: ``{field: (a's, b's)}``."""
    a, b = os.path.basename(a_file), os.path.basename(b_file)
    return ValueError(f"{a_file} and {b_file} disagree: " + "; ".join(f"{k}: {a} {va!r}, {b} {vb!r}"
                                                                      for k, (va, vb) in diff.items()))


def _common(a: Mapping[str, Any], b: Mapping[str, Any], a_file: str, b_file: str) -> None:
    """Every field both ``a`` (read from ``a_file``) and ``b`` hold must be equal."""
    diff = {k: (a[k], b[k]) for k in a if k in b and a[k] != b[k]}
    if diff:
        raise _disagree(a_file, b_file, diff)


def check_run_files(directory: str, config: Optional[SparseConfig], config_file: Optional[str]) -> None:
    """``ValueError`` naming both files and the fields when the files a run wrote beside its weights
    disagree (they describe one model; a disagreement is an edit or a mix of two runs, never used
    silently): ``train_config.json``'s ``sparse`` section and the sparse config (``config``, read
    from ``config_file``; but the fields set when the model is built, ``core.agreement.SET_WHEN_ATTACHED``),
    its ``model`` and ``backbone.json``, its ``text`` and ``text_encoder.json``, and
    ``diffusion_steps`` wherever it is held (``train_config.json``, ``motion.json``, an enabled
    sparse config). A text-conditioned ``backbone.json`` (``cond_mode: text``) needs its
    ``text_encoder.json`` unless the config swaps a text encoder in."""
    from ..reference.text import TEXT_CONFIG_FILENAME  # here: importing io loads no reference module

    join = lambda name: os.path.join(directory, name)  # noqa: E731
    bpath, tpath, text_path, mpath = (join(n) for n in (BACKBONE_FILENAME, TRAIN_CONFIG_FILENAME,
                                                         TEXT_CONFIG_FILENAME, MOTION_FILENAME))
    backbone = read_json_object(bpath) if os.path.exists(bpath) else None
    has_text = os.path.exists(text_path)
    if backbone is not None and backbone.get("cond_mode") == "text" and not has_text and not (
            config is not None and config.text_encoder):
        raise ValueError(f"{text_path}: missing, but {bpath} says cond_mode 'text' (a text-conditioned model; "
                         "smdm train --text writes it beside the weights); restore it from the run")
    steps: Dict[str, int] = {}
    if config is not None and config.enabled and config_file is not None:
        steps[config_file] = int(config.diffusion_steps)
    if os.path.exists(mpath):
        steps[mpath] = int_field(read_json_object(mpath), "diffusion_steps", mpath)
    if os.path.exists(tpath):
        train = read_json_object(tpath)
        if "diffusion_steps" in train:
            steps[tpath] = int_field(train, "diffusion_steps", tpath)
        _train_config_agrees(train, tpath, config, config_file)
        if backbone is not None and isinstance(train.get("model"), dict):
            _common(train["model"], backbone, tpath, bpath)
        text = train.get("text")
        if text is not None and not has_text:
            raise ValueError(f"{text_path}: missing, but {tpath} says the run was text-conditioned (text: {text!r})")
        if isinstance(text, dict):
            _common(text, read_json_object(text_path), tpath, text_path)
        elif text is None and has_text and "text" in train:
            raise ValueError(f"{tpath} and {text_path} disagree: text: {TRAIN_CONFIG_FILENAME} null (unconditional), "
                             f"{os.path.basename(text_path)} is there")
    files = list(steps)
    for other in files[1:]:
        if steps[other] != steps[files[0]]:
            raise _disagree(files[0], other, {"diffusion_steps": (steps[files[0]], steps[other])})


def _train_config_agrees(train: Mapping[str, Any], tpath: str, config: Optional[SparseConfig],
                         config_file: Optional[str]) -> None:
    """``train_config.json``'s ``sparse`` section (None: a dense run) against the sparse config."""
    if "sparse" not in train:
        return
    section = train["sparse"]
    if section is not None and not isinstance(section, Mapping):
        raise ValueError(f"{tpath}: sparse={section!r}: expected an object or null")
    dense = section is None or not section.get("enabled", True)
    if dense or config is None or config_file is None:
        if dense != (config is None or not config.enabled):
            there = f"{config_file} holds a sparse config" if config is not None else f"no {CONFIG_FILENAME} is beside it"
            raise ValueError(f"{tpath} says the run was {'dense' if dense else 'sparse'}, but {there}")
        return
    options = {"sparse": True, **{f"sparse_{k}": v for k, v in section.items() if k != "enabled"}}
    why = disagreement(config, options, config_file, tpath)
    if why:
        raise ValueError(why)


def read_state_dict(path: str, map_location: Any = "cpu", what: str = "checkpoint") -> Dict[str, Any]:
    """``torch.load(path, weights_only=True)`` with one-line errors naming the file (missing,
    empty, truncated or corrupt) and every floating tensor checked to be finite; complex tensors
    are refused. ``what`` names the file's role in messages."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such {what} file")
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a folder, expected a {what} file")
    if os.path.getsize(path) == 0:
        raise ValueError(f"{path}: empty {what} file (an interrupted write?)")
    try:
        obj = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises RuntimeError, EOFError, UnpicklingError, zipfile errors ...
        if isinstance(e, OSError) and not isinstance(e, EOFError):
            raise
        reason = " ".join(str(e).split()).split(". ")[0] or type(e).__name__   # its first sentence, whole
        reason = reason if len(reason) <= 200 else reason[:197] + "..."
        raise ValueError(f"{path}: not a readable {what} (truncated or corrupt: {reason})") from None
    if not isinstance(obj, Mapping):
        raise ValueError(f"{path}: expected a dict of tensors, got {type(obj).__name__}")
    for k, v in _tensors(obj):
        if v.is_complex():
            raise ValueError(f"{path}: tensor {k} is complex ({v.dtype}); expected real values")
        if v.is_floating_point() and v.numel() and not bool(torch.isfinite(v).all()):
            raise ValueError(f"{path}: tensor {k} holds non-finite values (nan/inf)")
    return dict(obj)


def _tensors(obj: Any, prefix: str = "") -> Iterable[Tuple[str, torch.Tensor]]:
    if isinstance(obj, torch.Tensor):
        yield prefix or "<root>", obj
    elif isinstance(obj, Mapping):
        for k, v in obj.items():
            yield from _tensors(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}[{i}]")


def state_dict_is_sparse(state_dict: Mapping[str, Any]) -> bool:
    """Whether ``state_dict`` comes from a sparsified model (it carries the marker buffer)."""
    return any(k == MARKER or k.endswith("." + MARKER) for k in state_dict)


def model_is_sparse(model: nn.Module) -> bool:
    """Whether ``model`` (or a submodule) carries the sparse marker buffer (any adapter)."""
    return state_dict_is_sparse(dict(model.named_buffers()))


def check_state_dict(model: nn.Module, state_dict: Mapping[str, Any], source: str = "checkpoint") -> None:
    """Raise a clear error when a sparse state dict meets a dense model or the reverse."""
    sd_sparse = state_dict_is_sparse(state_dict)
    model_sparse = model_is_sparse(model)
    if sd_sparse and not model_sparse:
        raise CheckpointMismatchError(
            f"{source} holds a SPARSE (sMDM) model but the model being loaded is dense. Re-create it "
            "sparse: keep args.json/sparse_config.json beside the weights and use the patched "
            "upstream (or `smdm run`), pass --sparse, or call smdm_plugin.load_checkpoint().")
    if model_sparse and not sd_sparse:
        raise CheckpointMismatchError(f"{source} holds a DENSE model but the model is sparse; load it into a dense "
                           "model (drop --sparse) or train a sparse one")


def unwrap_state_dict(obj: Any) -> Dict[str, torch.Tensor]:
    """A model state dict from what ``torch.load`` returned (MDM: raw dict or ``{'model': ...}``)."""
    if isinstance(obj, Mapping) and "model" in obj and isinstance(obj["model"], Mapping):
        return dict(obj["model"])
    if isinstance(obj, Mapping) and "state_dict" in obj:
        return dict(obj["state_dict"])
    return dict(obj)


def allowed_differences(allow_differences: Iterable[str]) -> Tuple[str, ...]:
    """``load_checkpoint``'s ``allow_differences``: field names of :class:`SparseConfig` (a string,
    which would be read letter by letter, is a ``TypeError``; an unknown name a ``ValueError``)."""
    import dataclasses

    if isinstance(allow_differences, (str, bytes)):
        raise TypeError(f"load_checkpoint: allow_differences must be a sequence of field names, got the string "
                        f"{allow_differences!r} (write ({allow_differences!r},))")
    try:
        allowed = tuple(allow_differences)
    except TypeError:
        raise TypeError(f"load_checkpoint: allow_differences must be a sequence of field names, got "
                        f"{type(allow_differences).__name__}") from None
    fields = [f.name for f in dataclasses.fields(SparseConfig)]
    unknown = [k for k in allowed if k not in fields]
    if unknown:
        raise ValueError(f"load_checkpoint: allow_differences names unknown SparseConfig field(s) {unknown}; "
                         f"known: {', '.join(fields)}")
    return allowed


def check_config_matches(current: Optional[SparseConfig], saved: SparseConfig, source: str,
                         allow_differences: Iterable[str] = ()) -> None:
    """Raise ``ValueError`` naming every field where an already-sparse model's config (``current``;
    None: the model is dense, nothing to compare) differs from the ``saved`` one (``version`` and
    the fields in ``allow_differences`` aside: :func:`allowed_differences`)."""
    allowed = allowed_differences(allow_differences)
    if current is None:
        return
    diff = saved.differences(current, ignore=("version", *allowed))
    if diff:
        listed = "; ".join(f"{k}: saved {a!r}, model {b!r}" for k, (a, b) in diff.items())
        raise ValueError(
            f"load_checkpoint: the model is already sparse, with a config that differs from the one saved "
            f"with the checkpoint ({source}) in {len(diff)} field(s): {listed}. Pass a dense model (it is "
            "sparsified with the saved config), sparsify it with find_sparse_config(path), or name the "
            "fields you changed on purpose in allow_differences=(...)")


def read_checkpoint(path: str, map_location: Any = "cpu"
                    ) -> Tuple[Dict[str, torch.Tensor], Optional[SparseConfig], Optional[str]]:
    """``(state dict, saved config or None, the file the config came from)`` of the ``.pt`` file
    ``path``; a sparse state dict without a config beside it is an error."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"load_checkpoint: no such checkpoint file: {path!r}")
    state = unwrap_state_dict(read_state_dict(path, map_location=map_location))
    config, source = find_config(path)
    if state_dict_is_sparse(state) and config is None:
        raise CheckpointMismatchError(f"load_checkpoint: {path} holds a sparse model but has no sparse config "
                                      f"beside it (expected {CONFIG_FILENAME} or args.json with sparse=true in "
                                      f"{_dir_of(path)})")
    return state, config, source


def build_backbone(path: str) -> nn.Module:
    """The in-package ``TinyMDM`` built from ``backbone.json`` beside the checkpoint ``path``."""
    bpath = os.path.join(_dir_of(path), BACKBONE_FILENAME)
    if not os.path.exists(bpath):
        raise FileNotFoundError(f"load_checkpoint: no model given and no {BACKBONE_FILENAME} beside "
                                f"{path} to build the in-package TinyMDM")
    from ..reference.backbone import TinyMDM

    backbone = read_json_object(bpath)
    try:
        return TinyMDM(**backbone)
    except (ValueError, TypeError) as e:
        raise ValueError(f"load_checkpoint: {bpath}: cannot build TinyMDM from it: {e}") from None


def load_weights(model: nn.Module, state: Mapping[str, Any], path: str, strict: bool = True,
                 config_file: Optional[str] = None) -> None:
    """Load ``state`` (read from ``path``) into ``model``, which must be sparse exactly when the
    state is, with every tensor of the model's shape and kind (a floating weight from a floating
    tensor: a bool or integer one would be cast without a word), the sparse marker holding the
    config's version; with ``strict``, a missing or unexpected key (CLIP's frozen weights aside) is
    an error. Errors (:class:`CheckpointMismatchError`) name ``path`` and the config it was read
    with (``config_file``), whose settings shaped the model."""
    check_state_dict(model, state, path)
    by = f" (the model was built as {config_file} describes: do the weights come from that run?)" if config_file else ""
    own = model.state_dict()
    for k, v in state.items():
        mine = own.get(k)
        if not isinstance(v, torch.Tensor) or not isinstance(mine, torch.Tensor):
            continue
        if tuple(v.shape) != tuple(mine.shape):
            raise CheckpointMismatchError(f"load_checkpoint: {path}: {k} has shape {tuple(v.shape)}, the model's "
                                          f"{tuple(mine.shape)}{by}")
        if mine.is_floating_point() and not v.is_floating_point():
            raise CheckpointMismatchError(f"load_checkpoint: {path}: {k} is {v.dtype}, expected a floating tensor "
                                          f"(the model's {mine.dtype})")
        if (k == MARKER or k.endswith("." + MARKER)) and v.numel() == 1 and int(v) != int(mine):
            raise CheckpointMismatchError(f"load_checkpoint: {path}: {k} is {int(v)}, but the config it is loaded "
                                          f"with has version {int(mine)}{by}")
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("clip_model.")]
    if strict and (missing or unexpected):
        raise CheckpointMismatchError(f"load_checkpoint: {path} does not match the model: missing {missing[:5]}, "
                                      f"unexpected {unexpected[:5]}{by}")
