"""SimpleDiffusion's schedule tables: cached per (device, dtype), bit for bit what indexing the
float64 host tables gives, and sampling unchanged."""
import torch

from smdm_plugin.reference.simple_diffusion import SimpleDiffusion


def _old_at(table: torch.Tensor, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The pre-cache lookup (copied the table to the device on every call)."""
    return table.to(like.device)[t].to(like.dtype).view(-1, *([1] * (like.dim() - 1)))


def test_tables_bit_identical_to_the_uncached_lookup():
    d = SimpleDiffusion(37)
    t = torch.tensor([0, 1, 17, 36, 5])
    host = {"sqrt_abar": d.abar.sqrt(), "sqrt_one_minus_abar": (1 - d.abar).sqrt(), "coef_x0": d.coef_x0,
            "coef_xt": d.coef_xt, "post_std": d.post_var.sqrt()}
    for dtype in (torch.float32, torch.float64, torch.bfloat16, torch.float16):
        like = torch.zeros(5, 3, 1, 8, dtype=dtype)
        for name, table in host.items():
            new, old = d._at(name, t, like), _old_at(table, t, like)
            assert new.dtype == dtype and new.shape == (5, 1, 1, 1)
            assert torch.equal(new, old), (name, dtype)


def test_tables_built_once_per_device_and_dtype():
    d = SimpleDiffusion(10)
    x = torch.randn(2, 4, 1, 6)
    t = torch.tensor([3, 9])
    d.q_sample(x, t)
    first = d.tables(x.device, x.dtype)
    d.q_sample(x, t)
    d.p_sample(lambda xt, tt, **kw: xt * 0.5, x, 4, {})
    assert len(d._tables) == 1
    assert all(d.tables(x.device, x.dtype)[k] is v for k, v in first.items())  # reused, not re-copied
    d.q_sample(x.double(), t)
    assert len(d._tables) == 2 and d.tables(x.device, torch.float64)["coef_x0"].dtype == torch.float64


def test_sampling_unchanged_by_the_cache():
    """The loop through the cached tables equals a loop written with the uncached lookup."""
    d = SimpleDiffusion(12)
    model = lambda xt, tt, **kw: torch.tanh(xt) * (1 + tt.view(-1, 1, 1, 1).float() / 12)  # noqa: E731
    shape = (3, 5, 1, 7)
    out = d.p_sample_loop(model, shape, generator=torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(4)
    x = torch.randn(shape, generator=g)
    for t in range(11, -1, -1):
        tt = torch.full((3,), t, dtype=torch.long)
        x0 = model(x, tt)
        if t == 0:
            x = x0
            break
        mean = _old_at(d.coef_x0, tt, x) * x0 + _old_at(d.coef_xt, tt, x) * x
        x = mean + _old_at(d.post_var.sqrt(), tt, x) * torch.randn(shape, generator=g)
    assert torch.equal(out, x)
