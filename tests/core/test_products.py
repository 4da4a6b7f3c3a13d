"""What calls without autograd make from parameters alone (core/products.py): kept while the inputs
are unchanged, remade in place when one changes, read by a trace only when armed, and refreshed
for a whole model by one key check."""
from __future__ import annotations

import copy

import torch
from torch import nn

from smdm_plugin.core.fsq import FSQMultiheadAttention, folded_projections
from smdm_plugin.core.lipschitz import LipschitzMLP
from smdm_plugin.core.products import ProductStore, armed_products, products_armed, refresh_products


def _store_with(w: torch.Tensor):
    calls = []

    def make(dtype=torch.float32):
        calls.append(dtype)
        return ((w * 2).to(dtype), (w.sum(0) + 1).to(dtype))

    return ProductStore(), make, calls


def test_kept_while_unchanged_and_remade_in_place_after_an_update():
    w = torch.randn(3, 4)
    store, make, calls = _store_with(w)
    first = store.get(torch.float32, [w], make)
    assert store.get(torch.float32, [w], make) is first and len(calls) == 1
    ptrs = [t.data_ptr() for t in first]
    with torch.no_grad():
        w.mul_(-3.0)                                          # an optimizer step: the version moves
    again = store.get(torch.float32, [w], make)
    assert len(calls) == 2 and again is first and [t.data_ptr() for t in again] == ptrs
    torch.testing.assert_close(again[0], w * 2, rtol=0, atol=0)
    torch.testing.assert_close(again[1], w.sum(0) + 1, rtol=0, atol=0)
    w2 = torch.randn(3, 4)                                    # another tensor: its storage is the key
    store2 = store.get(torch.float32, [w2], lambda: ((w2 * 2), (w2.sum(0) + 1)))
    assert store2 is first and torch.equal(store2[0], w2 * 2)


def test_a_new_layout_gets_new_tensors_and_views_get_storages_of_their_own():
    w = torch.randn(4, 4)
    store = ProductStore()
    held = store.get(torch.float32, [w], lambda: tuple(w.unbind(0)))     # views of w
    assert all(t._base is None for t in held) and held[0].data_ptr() != w.data_ptr()
    with torch.no_grad():
        w.add_(1.0)
    bigger = store.get(torch.float32, [w], lambda: (torch.cat([w, w]),))  # another layout
    assert bigger is not held and bigger[0].shape == (8, 4)


def test_an_input_handed_back_is_held_as_a_copy_never_written_by_the_store():
    """A product equal to an input (a cast to the dtype it has already) is held in a storage of its
    own: remaking it in place writes the store's copy, never the input (whose version would move
    and make every call a miss)."""
    w = torch.randn(3, 4)
    store = ProductStore()
    held = store.get(torch.float32, [w], lambda: (w, w.t()))
    assert held[0] is not w and held[0].data_ptr() != w.data_ptr() and held[1]._base is None
    with torch.no_grad():
        w.add_(1.0)
    version = w._version
    again = store.get(torch.float32, [w], lambda: (w, w.t()))
    assert again is held and w._version == version and torch.equal(again[0], w) and torch.equal(again[1], w.t())
    assert store.get(torch.float32, [w], lambda: (w, w.t())) is held and w._version == version


def test_a_store_that_is_not_static_replaces_what_it_handed_out():
    """``static=False``: a remade value is a new tensor, the one handed out keeps its values (what a
    user may hold, such as a parametrized weight read without autograd)."""
    w = torch.randn(3, 4)
    store = ProductStore(static=False)
    first = store.get(torch.float32, [w], lambda: (w * 2,))
    kept = first[0].clone()
    with torch.no_grad():
        w.mul_(-1.0)
    again = store.get(torch.float32, [w], lambda: (w * 2,))
    assert again[0] is not first[0] and torch.equal(first[0], kept) and torch.equal(again[0], w * 2)


def test_refresh_remakes_every_dtype_held_and_read_needs_arming():
    w = torch.randn(3, 4)
    store, make, calls = _store_with(w)
    store.get(torch.bfloat16, [w], lambda: make(torch.bfloat16))
    with torch.no_grad():
        w.add_(0.5)
    out = store.refresh(torch.float32, [w], make)
    assert sorted(map(str, calls)) == ["torch.bfloat16", "torch.bfloat16", "torch.float32"]
    torch.testing.assert_close(store.tensors[torch.bfloat16][0], (w * 2).bfloat16(), rtol=0, atol=0)
    assert out is store.tensors[torch.float32]
    assert store.read(torch.float32) is None and not products_armed()
    with armed_products():
        assert store.read(torch.float32) is out and store.read(torch.float16) is None
        with armed_products(False):
            assert store.read(torch.float32) is None
        assert products_armed()
    assert not products_armed()


class _Model(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.inp = LipschitzMLP(5, 8)
        self.attn = FSQMultiheadAttention(8, 2, levels=(8, 5, 5))


def _expected(model: _Model, dtype=torch.float32):
    w, b = folded_projections([model.attn], dtype)[0]
    mlp = [m for m in model.inp.net if isinstance(m, nn.Linear)]
    return (w, b), tuple(m.weight.detach().to(dtype) for m in mlp)


def test_a_model_is_refreshed_by_one_key_check_and_follows_updates_and_new_modules():
    torch.manual_seed(0)
    model = _Model()
    with torch.no_grad():
        refresh_products(model)
        seen = []
        for m in (model.inp, model.attn):
            m.refresh_products = (lambda f: lambda *a: seen.append(f) or f(*a))(m.refresh_products)
        refresh_products(model)
        assert seen == []                                       # nothing changed: one key check
        for p in model.parameters():
            p.mul_(1.5)
        refresh_products(model)
        assert len(seen) == 2
        (w, b), lip = _expected(model)
        held_w, held_b = model.attn.products().tensors[torch.float32]
        torch.testing.assert_close(held_w, w, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(held_b, b, rtol=1e-6, atol=1e-6)
        for held, want in zip(model.inp.products().tensors[torch.float32], lip):
            torch.testing.assert_close(held, want, rtol=1e-6, atol=1e-6)
        with torch.autocast("cpu", dtype=torch.bfloat16):      # another compute dtype: refreshed too
            refresh_products(model)
        assert torch.bfloat16 in model.attn.products().tensors
        model.out = LipschitzMLP(8, 5)                          # a registration: the holders are found again
        refresh_products(model)
        assert torch.float32 in model.out.products().tensors


def test_a_deep_copy_keeps_products_of_its_own_weights():
    torch.manual_seed(1)
    model = _Model()
    with torch.no_grad():
        refresh_products(model)
        twin = copy.deepcopy(model)
        for p in twin.parameters():
            p.neg_()
        refresh_products(twin)
        refresh_products(model)
    (w, _), _ = _expected(model)
    (w2, _), _ = _expected(twin)
    torch.testing.assert_close(model.attn.products().tensors[torch.float32][0], w, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(twin.attn.products().tensors[torch.float32][0], w2, rtol=1e-6, atol=1e-6)
    assert not torch.allclose(w, w2)


def test_products_made_under_inference_mode_are_replaced_outside_it():
    """A store filled under ``torch.inference_mode`` (no in-place write outside it) is remade as new
    tensors by a later call without it, after an update."""
    w = torch.randn(3, 4)
    store, make, _ = _store_with(w)
    with torch.inference_mode():
        first = store.get(torch.float32, [w], make)
    assert first[0].is_inference()
    with torch.no_grad():
        w.add_(1.0)
        again = store.get(torch.float32, [w], make)
    assert again is not first and torch.equal(again[0], w * 2)


def test_a_deep_copy_of_a_sparse_model_remakes_its_caches_from_its_own_weights():
    """Every cache of values made from tensors alone (the stores, the eager stack's layout, the
    weight casts' parameter lists) deep-copies as nothing (an EMA copy): the copy samples as the
    original, under autocast too, and follows its own weights, not the original's. (A sparse model
    is not picklable whole: torch refuses parametrized modules; a dense model's casts pickle as
    nothing too, the same method.)"""
    from smdm_plugin.adapters.surgery import sparsify
    from smdm_plugin.core.config import SparseConfig
    from smdm_plugin.core.products import Remade
    from smdm_plugin.core.weight_casts import refresh_casts
    from smdm_plugin.reference.backbone import TinyMDM

    torch.manual_seed(0)
    model = sparsify(TinyMDM(latent_dim=32, ff_size=64, num_layers=2, dropout=0.0, cond_mask_prob=0.0),
                     SparseConfig()).eval()
    B, N = 2, 30
    g = torch.Generator().manual_seed(0)
    x, t = torch.randn(B, 263, 1, N, generator=g), torch.tensor([3, 7])
    y = {"mask": torch.ones(B, 1, 1, N, dtype=torch.bool), "lengths": torch.full((B,), N),
         "text_embed": torch.randn(1, B, 512, generator=g)}

    def run(m):
        with torch.no_grad():
            plain = m(x, t, y=dict(y))
            with torch.autocast("cpu", torch.bfloat16):
                refresh_casts(m, "cpu")
                low = m(x, t, y=dict(y))
        return plain, low

    want = run(model)

    def caches(m):
        return [v for mod in m.modules() for v in vars(mod).values() if isinstance(v, Remade)]

    assert len(caches(model)) >= 4                        # stores, the stack, the casts' list, the holders
    twin = copy.deepcopy(model)
    assert caches(twin) == []
    got = run(twin)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    with torch.no_grad():
        for p in twin.parameters():
            p.mul_(0.5)
    changed = run(twin)
    assert not torch.equal(changed[0], want[0]) and not torch.equal(changed[1], want[1])
    for a, b in zip(run(model), want):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
