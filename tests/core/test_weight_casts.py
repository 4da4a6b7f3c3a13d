"""core/weight_casts.py: which parameters a compiled call without autograd reads in autocast's dtype,
and their casts kept while the parameters are unchanged."""
import torch
from torch import nn

from smdm_plugin.core.lipschitz import lipschitz_linear
from smdm_plugin.core.weight_casts import cast_parameters, refresh_casts


class Net(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(4, 8)
        self.attn = nn.MultiheadAttention(8, 2)                  # in_proj + out_proj (a linear subclass)
        self.norm = nn.LayerNorm(8)                              # autocast runs it in float32
        self.emb = nn.Embedding(5, 8)
        self.lip = lipschitz_linear(8, 8)                        # weight parametrized: its bias only
        self.frozen = nn.Linear(8, 8).requires_grad_(False)      # (a frozen text encoder)
        self.a, self.b = nn.Linear(8, 8), nn.Linear(8, 8)
        self.b.weight = self.a.weight                            # read by two modules
        self.wide = nn.Linear(8, 8).double()
        self.conv = nn.Conv1d(8, 8, 1)


def test_cast_parameters_are_the_matmul_only_parameters():
    names = [n for n, _ in cast_parameters(Net())]
    assert names == ["lin.weight", "lin.bias", "attn.in_proj_weight", "attn.in_proj_bias", "attn.out_proj.weight",
                     "attn.out_proj.bias", "lip.bias", "a.bias", "b.bias"]


def test_casts_are_autocasts_values_kept_while_unchanged_and_remade_in_place():
    net = Net()
    assert refresh_casts(net, "cpu") is None                                   # no autocast
    with torch.autocast("cpu", torch.bfloat16):
        casts = refresh_casts(net, "cpu", "m.")
        again = refresh_casts(net, "cpu", "m.")
    assert again is casts and sorted(casts) == sorted("m." + n for n, _ in cast_parameters(net))
    params = dict(net.named_parameters())
    for name, t in casts.items():
        assert t.dtype == torch.bfloat16 and torch.equal(t, params[name[2:]].detach().to(torch.bfloat16))
    held = casts["m.lin.weight"]
    with torch.no_grad():
        net.lin.weight.add_(1.0)                                               # an optimizer step
    with torch.autocast("cpu", torch.bfloat16):
        casts = refresh_casts(net, "cpu", "m.")
    assert casts["m.lin.weight"] is held and torch.equal(held, net.lin.weight.detach().to(torch.bfloat16))
    assert net.lin.weight.dtype == torch.float32 and isinstance(net.lin.weight, nn.Parameter)


def test_no_casts_without_autocast_or_where_it_keeps_the_parameters_dtype():
    net = nn.Sequential(nn.Linear(4, 4))
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=False):
        assert refresh_casts(net, "cpu") is None
    with torch.autocast("cpu", torch.bfloat16):
        assert refresh_casts(net, "meta") is None                             # no autocast state there
        assert refresh_casts(net.double(), "cpu") is None                      # autocast leaves float64 alone
