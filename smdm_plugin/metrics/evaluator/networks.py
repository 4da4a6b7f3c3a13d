"""The three networks of the T2M evaluator (Guo et al., CVPR 2022, Sec. 3 and supp.), written from
the paper's description; the attribute names and parameter shapes are those of the published
checkpoint (``text_mot_match/model/finest.tar``: ``movement_encoder``, ``motion_encoder``,
``text_encoder``), so its state dicts load into them unchanged."""
from __future__ import annotations

import torch
import torch.nn as nn
from torch.nn.utils.rnn import pack_padded_sequence


class MovementConvEncoder(nn.Module):
    """``[B, N, input_size] -> [B, N // 4, output_size]`` (N a multiple of 4)."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, kernel_size=4, stride=2, padding=1),
            nn.Dropout(0.2), nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, kernel_size=4, stride=2, padding=1),
            nn.Dropout(0.2), nn.LeakyReLU(0.2))
        self.out_net = nn.Linear(output_size, output_size)
        _xavier(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out_net(self.main(x.transpose(1, 2)).transpose(1, 2))


class MovementConvDecoder(nn.Module):
    """The movement auto-encoder's decoder (training only, T2M's decomposition stage):
    ``[B, S, input_size] -> [B, 4 S, output_size]`` (two transposed convolutions, kernel 4, stride 2)."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.ConvTranspose1d(input_size, hidden_size, kernel_size=4, stride=2, padding=1), nn.LeakyReLU(0.2),
            nn.ConvTranspose1d(hidden_size, output_size, kernel_size=4, stride=2, padding=1), nn.LeakyReLU(0.2))
        self.out_net = nn.Linear(output_size, output_size)
        _xavier(self)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.out_net(self.main(z.transpose(1, 2)).transpose(1, 2))


class _BiGRUCo(nn.Module):
    """Shared body of the two co-embedding encoders: ``input_emb``, ``gru``, ``output_net``, ``hidden``."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(nn.Linear(2 * hidden_size, hidden_size), nn.LayerNorm(hidden_size),
                                        nn.LeakyReLU(0.2), nn.Linear(hidden_size, output_size))
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden_size))  # learned initial state (fwd, bwd)
        self.hidden_size = hidden_size
        _xavier(self.input_emb)
        _xavier(self.output_net)

    def _encode(self, inputs: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """``inputs [B, S, input_size]``, ``lengths [B]`` (each in ``[1, S]``) -> ``[B, output_size]``."""
        packed = pack_padded_sequence(self.input_emb(inputs), lengths.detach().cpu().long(), batch_first=True,
                                      enforce_sorted=False)
        _, last = self.gru(packed, self.hidden.expand(-1, inputs.shape[0], -1).contiguous())
        return self.output_net(torch.cat([last[0], last[1]], dim=-1))


class MotionEncoderBiGRUCo(_BiGRUCo):
    """Movement steps ``[B, S, input_size]`` with ``lengths [B]`` (steps) -> co-embedding ``[B, output_size]``."""

    def forward(self, movements: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return self._encode(movements, lengths)


class TextEncoderBiGRUCo(_BiGRUCo):
    """Word vectors ``[B, T, word_size]`` + part-of-speech one-hots ``[B, T, pos_size]`` with token
    counts ``lengths [B]`` -> co-embedding ``[B, output_size]``."""

    def __init__(self, word_size: int, pos_size: int, hidden_size: int, output_size: int) -> None:
        super().__init__(word_size, hidden_size, output_size)
        self.pos_emb = nn.Linear(pos_size, word_size)
        _xavier(self.pos_emb)

    def forward(self, words: torch.Tensor, pos_onehot: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return self._encode(words + self.pos_emb(pos_onehot), lengths)


def _xavier(module: nn.Module) -> None:
    """Xavier-normal weights, zero biases for the convolutions and linear layers (as the paper's code)."""
    for m in module.modules():
        if isinstance(m, (nn.Conv1d, nn.ConvTranspose1d, nn.Linear)):
            nn.init.xavier_normal_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
