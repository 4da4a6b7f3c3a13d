"""Tiny random ``transformers`` text encoders saved to a folder, built offline (no download), for
the text-encoder tests (unit and upstream integration).

``make_tiny_encoder(path, st=None)``: a 2-layer random BERT from a transformers config plus a
word-level tokenizer (``tokenizers``) over a small motion vocabulary,
saved with ``save_pretrained``. ``st`` adds a sentence-transformers layout (``modules.json``,
``1_Pooling``, optionally a ``2_Dense`` head and ``Normalize``), as stella_en_1.5B_v5 has:
``dict(pooling="mean", dense=24, activation="Identity", normalize=False, prompt=None)``.

The modules that use them run on one thread (tests/conftest.py's ``one_thread`` fixture).
"""
from __future__ import annotations

import json
import os
from typing import Any, Dict, Optional

import torch

WORDS = ("a person walks forward and then turns left right slowly quickly jumps up down runs in a circle "
         "sits on the ground stands waves with hand kicks throws ball dances steps back bends over picks "
         "something").split()


def _tokenizer(padding_side: str = "right"):
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    vocab: Dict[str, int] = {}
    for w in ["[PAD]", "[UNK]", "[CLS]", "[SEP]"] + list(WORDS):
        vocab.setdefault(w, len(vocab))
    tok = Tokenizer(models.WordLevel(vocab=vocab, unk_token="[UNK]"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, unk_token="[UNK]", pad_token="[PAD]",
                                   cls_token="[CLS]", sep_token="[SEP]", padding_side=padding_side)
    return fast, len(vocab)


def _model(vocab: int, hidden: int, seed: int, dropout: float):
    from transformers import BertConfig, BertModel

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        cfg = BertConfig(vocab_size=vocab, hidden_size=hidden, num_hidden_layers=2, num_attention_heads=2,
                         intermediate_size=2 * hidden, max_position_embeddings=64,
                         hidden_dropout_prob=dropout, attention_probs_dropout_prob=dropout)
        return BertModel(cfg)


def _write_json(path: str, obj: Any) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=2)


def make_tiny_encoder(path: str, hidden: int = 32, seed: int = 0, st: Optional[Dict[str, Any]] = None,
                      padding_side: str = "right", dropout: float = 0.1) -> str:
    """Save a tiny random encoder (and tokenizer) into ``path``; returns ``path``."""
    tokenizer, vocab = _tokenizer(padding_side)
    model = _model(vocab, hidden, seed, dropout)
    model.save_pretrained(path)
    tokenizer.save_pretrained(path)
    if st is not None:
        modules = [{"idx": 0, "name": "0", "path": "", "type": "sentence_transformers.models.Transformer"},
                   {"idx": 1, "name": "1", "path": "1_Pooling", "type": "sentence_transformers.models.Pooling"}]
        pooling = st.get("pooling", "mean")
        key = {"mean": "pooling_mode_mean_tokens", "cls": "pooling_mode_cls_token",
               "last": "pooling_mode_lasttoken", "max": "pooling_mode_max_tokens"}[pooling]
        _write_json(os.path.join(path, "1_Pooling", "config.json"),
                    {"word_embedding_dimension": hidden, "pooling_mode_cls_token": False,
                     "pooling_mode_mean_tokens": False, "pooling_mode_max_tokens": False,
                     "pooling_mode_mean_sqrt_len_tokens": False, key: True})
        if st.get("dense"):
            folder = st.get("dense_folder", "2_Dense")
            modules.append({"idx": 2, "name": "2", "path": folder, "type": "sentence_transformers.models.Dense"})
            act = st.get("activation", "Identity")
            module = "linear" if act == "Identity" else "activation"
            _write_json(os.path.join(path, folder, "config.json"),
                        {"in_features": hidden, "out_features": int(st["dense"]), "bias": True,
                         "activation_function": f"torch.nn.modules.{module}.{act}"})
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed + 1)
                lin = torch.nn.Linear(hidden, int(st["dense"]))
            from safetensors.torch import save_file

            save_file({"linear.weight": lin.weight.detach().contiguous(),
                       "linear.bias": lin.bias.detach().contiguous()},
                      os.path.join(path, folder, "model.safetensors"))
        if st.get("normalize"):
            modules.append({"idx": len(modules), "name": str(len(modules)), "path": "3_Normalize",
                            "type": "sentence_transformers.models.Normalize"})
        _write_json(os.path.join(path, "modules.json"), modules)
        prompts = {"default_prompt_name": None, "prompts": {}}
        if st.get("prompt"):
            prompts = {"default_prompt_name": "motion", "prompts": {"motion": st["prompt"]}}
        _write_json(os.path.join(path, "config_sentence_transformers.json"), prompts)
    return path


def dense_head(path: str, folder: str = "2_Dense") -> torch.nn.Linear:
    """The ``Dense`` head saved by :func:`make_tiny_encoder`, as a plain ``nn.Linear`` (reference)."""
    from safetensors.torch import load_file

    state = load_file(os.path.join(path, folder, "model.safetensors"))
    lin = torch.nn.Linear(state["linear.weight"].shape[1], state["linear.weight"].shape[0])
    lin.load_state_dict({"weight": state["linear.weight"], "bias": state["linear.bias"]})
    return lin
