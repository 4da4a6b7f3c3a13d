"""DoubleTake forced keyframes: geometry, y-derived forcing, and that the sparse model honours them
at every sampling step of both takes (TinyMDM stand-in, a DoubleTake-shaped sampling loop)."""
import argparse
import warnings

import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM, sparsify
from smdm_plugin.core.selection import keyframe_count
from smdm_plugin.adapters.request import KEYFRAMES_KEY
from smdm_plugin.adapters.state import get_state
from smdm_plugin.families.doubletake.model import (PAPER_BLEND_LEN, attach_doubletake_forcing, has_doubletake_forcing,
                                             detach_doubletake_forcing, doubletake_forced_bound,
                                             doubletake_forced_frames, doubletake_forced_from_y, paper_blend_len)
from smdm_plugin.families.doubletake.upstream import sparsify_priormdm
from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

H, BLEND = 6, 4


def _first_take_transition(lengths, n):
    """priorMDM's ``is_transition`` of the first take (written from its description)."""
    S = len(lengths)
    tr = torch.zeros(S, n)
    for i, L in enumerate(lengths):
        if i > 0:
            tr[i, :H] = 1
        if i < S - 1:
            tr[i, L - H:L] = 1
    return tr


def _second_take_inpainting(lengths, n2, feats, blend=BLEND):
    """priorMDM's second-take ``inpainting_mask`` (utils/sampling_utils.py, written from its
    description): 1 = keep; ramps 0.85 -> 0 before each handshake and 0 -> 0.85 after it, only
    when ``blend >= 2``."""
    m = torch.ones(len(lengths) - 1, feats, 1, n2)
    for i in range(len(lengths) - 1):
        b = lengths[i] - 2 * H
        if blend >= 2:
            m[i, :, :, b - blend:b] = torch.linspace(0.85, 0.85 / blend, blend)
            m[i, :, :, b + H:b + H + blend] = torch.arange(0.0, 0.85, 0.85 / blend)[:blend]
    return m


def test_forced_geometry_first_take():
    f = doubletake_forced_frames([30, 40, 25], H)
    assert f.shape == (3, 40)
    assert f[0].nonzero().flatten().tolist() == list(range(24, 30))
    assert f[1].nonzero().flatten().tolist() == list(range(0, 6)) + list(range(34, 40))
    assert f[2].nonzero().flatten().tolist() == list(range(0, 6))
    tr = _first_take_transition([30, 40, 25], 40)
    assert torch.equal(f, tr.bool())
    assert torch.equal(doubletake_forced_from_y({"is_transition": tr}, 3, 40), f)


def test_forced_geometry_second_take():
    lens = [30, 40, 25]
    f = doubletake_forced_frames(lens, H, take="second", blend_len=BLEND)
    n2 = (40 - 2 * H) * 2 + H
    assert f.shape == (2, n2)
    for i in range(2):
        b = lens[i] - 2 * H
        assert f[i].nonzero().flatten().tolist() == list(range(b - BLEND, b + H + BLEND))
    y = {"inpainting_mask": _second_take_inpainting(lens, n2, 5),
         "is_transition": torch.zeros(2, n2)}
    assert torch.equal(doubletake_forced_from_y(y, 2, n2), f)


def test_no_forcing_without_doubletake_keys():
    assert doubletake_forced_from_y({"lengths": torch.tensor([3])}, 1, 10) is None


def _sparse_tiny(reduction=0.8):
    torch.manual_seed(0)
    model = TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=2,
                    cond_mode="no_cond", dropout=0.0).eval()
    cfg = SparseConfig(reduction=reduction, feature="raw", diffusion_steps=10, gamma=0.5)
    sparsify(model, cfg)
    attach_doubletake_forcing(model)
    seen = []
    tr = model.seqTransEncoder
    orig = tr.set_plan

    def spy(plan):
        if plan is not None:
            seen.append(plan.mask.clone())
        orig(plan)

    tr.set_plan = spy
    return model, seen


def test_forced_frames_honoured_every_step():
    lens = [30, 40, 25]
    S, n = len(lens), max(lens)
    model, seen = _sparse_tiny()
    diff = SimpleDiffusion(10)
    y = {"lengths": torch.tensor(lens), "is_transition": _first_take_transition(lens, n),
         "mask": (torch.arange(n)[None] < torch.tensor(lens)[:, None]).view(S, 1, 1, n)}
    # first take: handshake blend after every step, as priorMDM's p_sample_loop does
    x = torch.randn(S, 8, 1, n)
    alpha = torch.arange(H) / H
    for t in range(9, -1, -1):
        x = diff.p_sample(model, x, t, {"y": y})
        for i in range(1, S):
            L = lens[i - 1]
            blend = x[i - 1, ..., L - H:L] * (1 - alpha) + x[i, ..., :H] * alpha
            x[i - 1, ..., L - H:L] = blend
            x[i, ..., :H] = blend
    first = doubletake_forced_frames(lens, H)
    assert len(seen) == 10
    for mask in seen:
        assert bool(mask[first].all())
        assert int(mask.sum()) < int(y["mask"].sum())  # still sparse elsewhere
    assert KEYFRAMES_KEY not in y  # the caller's dict is untouched

    # second take: inpainting of the transition windows
    seen.clear()
    n2 = (n - 2 * H) * 2 + H
    lens2 = torch.tensor([lens[i] + lens[i + 1] - 3 * H for i in range(S - 1)])
    y2 = {"lengths": lens2, "is_transition": torch.zeros(S - 1, n2),
          "inpainting_mask": _second_take_inpainting(lens, n2, 8),
          "mask": (torch.arange(n2)[None] < lens2[:, None]).view(S - 1, 1, 1, n2)}
    x2 = torch.randn(S - 1, 8, 1, n2)
    for t in range(4, -1, -1):
        x2 = diff.p_sample(model, x2, t, {"y": y2})
    second = doubletake_forced_frames(lens, H, take="second", blend_len=BLEND)
    assert len(seen) == 5
    for mask in seen:
        assert bool(mask[second].all())


def test_detach():
    model, seen = _sparse_tiny()
    assert has_doubletake_forcing(model)
    detach_doubletake_forcing(model)
    assert not has_doubletake_forcing(model) and not model._forward_pre_hooks_with_kwargs.get(-1, False)
    lens = [30, 40]
    y = {"lengths": torch.tensor(lens), "is_transition": _first_take_transition(lens, 40)}
    with torch.no_grad():
        model(torch.randn(2, 8, 1, 40), torch.tensor([9, 9]), y)
    forced = doubletake_forced_frames(lens, H)
    assert not bool(seen[-1][forced].all())  # uniform mask at t=9 misses most handshake frames


# --------------------------------------------------------------------------- blend length
def test_paper_blend_length_is_the_default():
    assert paper_blend_len(20) == PAPER_BLEND_LEN == 5  # 0.25 s at HumanML3D's 20 fps
    assert paper_blend_len(30) == 8 and paper_blend_len(12.5) == 3
    with pytest.raises(ValueError, match="fps must be > 0"):
        paper_blend_len(0)
    lens = [30, 40, 25]
    f = doubletake_forced_frames(lens, H, take="second")  # no blend_len given: the paper's
    for i in range(2):
        b = lens[i] - 2 * H
        assert f[i].nonzero().flatten().tolist() == list(range(b - 5, b + H + 5))


@pytest.mark.parametrize("blend", [0, 1, 2, 5, 7])
def test_second_take_geometry_matches_priormdm_mask_for_every_blend(blend):
    lens = [30, 40, 25]
    n2 = (40 - 2 * H) * 2 + H
    geo = doubletake_forced_frames(lens, H, take="second", blend_len=blend)
    y = {"inpainting_mask": _second_take_inpainting(lens, n2, 3, blend), "is_transition": torch.zeros(2, n2)}
    assert torch.equal(doubletake_forced_from_y(y, 2, n2), geo)
    assert int(geo.sum()) == (0 if blend < 2 else 2 * (2 * blend + H))  # no ramp, nothing regenerated


class doubleTake_TinyMDM(TinyMDM):  # noqa: N801 - named like priorMDM's doubleTake_MDM
    pass


@pytest.mark.parametrize("blend,warns", [(20, True), (10, True), (5, False), (None, False)])
def test_sparse_doubletake_warns_about_a_non_paper_blend(blend, warns):
    torch.manual_seed(0)
    model = doubleTake_TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
    args = argparse.Namespace(sparse=True, sparse_feature="raw")
    if blend is not None:
        args.blend_len = blend
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sparsify_priormdm(model, args)
    hit = [str(w.message) for w in caught if "--blend_len" in str(w.message)]
    assert bool(hit) == warns
    if warns:
        assert "--blend_len 5" in hit[0] and ("priorMDM's default" in hit[0]) == (blend == 20)
    assert has_doubletake_forcing(model)  # forcing attached either way


def test_forced_frames_count_inside_the_budget():
    """Issue 11: DoubleTake's forced handshake / inpainting frames are part of the K keyframes, not
    added on top: every segment keeps max(K, its protected frames), all forced frames among them."""
    lens = [60, 60, 60]
    n = max(lens)
    model, seen = _sparse_tiny(reduction=0.8)
    y = {"lengths": torch.tensor(lens), "is_transition": _first_take_transition(lens, n),
         "mask": (torch.arange(n)[None] < torch.tensor(lens)[:, None]).view(3, 1, 1, n)}
    with torch.no_grad():
        model(torch.randn(3, 8, 1, n), torch.tensor([9, 9, 9]), y)
    forced = doubletake_forced_frames(lens, H)
    K = keyframe_count(60, 0.8)
    protected = (forced | (torch.arange(n) == 0) | (torch.arange(n) == n - 1)).sum(1)
    assert (protected <= K).all()                                      # the budget can hold them
    assert seen[-1][forced].all()
    assert seen[-1].sum(1).tolist() == [K] * 3                          # K, not K + forced


# --------------------------------------------------------------------------- no host sync
def _close_gaps_reference(free, max_gap):
    """0.9.1's loop (a host read per row): fill runs of False of length <= max_gap between two Trues."""
    out = free.clone()
    for b in range(free.shape[0]):
        idx = free[b].nonzero(as_tuple=True)[0].tolist()
        for a, c in zip(idx[:-1], idx[1:]):
            if 1 < c - a <= max_gap + 1:
                out[b, a:c] = True
    return out


def test_closing_gaps_on_the_device_equals_the_loop():
    from smdm_plugin.families.doubletake.model import _close_gaps

    g = torch.Generator().manual_seed(0)
    for p in (0.05, 0.2, 0.5):
        free = torch.rand(64, 50, generator=g) < p
        free[0] = False
        free[1] = True
        for max_gap in (0, 1, 3, 7, 50):
            assert torch.equal(_close_gaps(free, max_gap), _close_gaps_reference(free, max_gap)), (p, max_gap)


@pytest.mark.parametrize("h,blend", [(6, 4), (6, 1), (20, 20), (20, 5), (3, 0)])
def test_the_forced_bound_holds_for_both_takes(h, blend):
    from smdm_plugin.families.doubletake.model import doubletake_forced_bound

    bound = doubletake_forced_bound(h, blend)
    for lens in ([30, 40, 25], [60, 60, 60, 60], [2 * h + 12, 5 * h]):
        first = doubletake_forced_frames(lens, h)
        second = doubletake_forced_frames(lens, h, take="second", blend_len=blend)
        assert int(first.sum(1).max()) <= bound and int(second.sum(1).max()) <= bound
    assert bound == max(int(doubletake_forced_frames([60, 60, 60], h).sum(1).max()),
                        int(doubletake_forced_frames([60, 60, 60], h, take="second", blend_len=blend).sum(1).max()))
    with pytest.raises(ValueError, match="handshake_size and blend_len"):
        doubletake_forced_bound(-1, 2)


def _doubletake_calls(model, lens, n):
    """A first-take and a second-take call's inputs (priorMDM's geometry)."""
    S = len(lens)
    n2 = (max(lens) - 2 * H) * 2 + H
    first = (torch.randn(S, 8, 1, n), {"lengths": torch.tensor(lens), "is_transition": _first_take_transition(lens, n),
                                       "mask": (torch.arange(n)[None] < torch.tensor(lens)[:, None]).view(S, 1, 1, n)})
    lens2 = [lens[i] + lens[i + 1] - 3 * H for i in range(S - 1)]
    second = (torch.randn(S - 1, 8, 1, n2),
              {"lengths": torch.tensor(lens2), "is_transition": torch.zeros(S - 1, n2),
               "inpainting_mask": _second_take_inpainting(lens, n2, 8),
               "mask": (torch.arange(n2)[None] < torch.tensor(lens2)[:, None]).view(S - 1, 1, 1, n2)})
    return first, second


def test_with_the_run_bound_a_doubletake_call_reads_nothing_on_the_host():
    """``attach_doubletake_forcing(model, forced_bound=...)`` (the priorMDM integration passes
    ``doubletake_forced_bound(--handshake_size, --blend_len)``): both takes' sampling calls make no
    host sync (counted as CUDA runs them) and give what the reading calls give; without the bound a
    call reads its forced frames (one sync), once per tensor: a loop's next call with the same
    tensors looks its plan up (no sync either way)."""
    from smdm_plugin.core.checks import static_mode
    from smdm_plugin.families.doubletake.model import doubletake_forced_bound
    from smdm_plugin.runtime.launches import count_launches

    lens = [30, 40, 25]
    model, seen = _sparse_tiny()
    calls = _doubletake_calls(model, lens, max(lens))
    results = {}
    for bound in (None, doubletake_forced_bound(H, BLEND)):
        attach_doubletake_forcing(model, forced_bound=bound)
        for take, (x, y) in zip(("first", "second"), calls):
            fresh = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in y.items()}
            with torch.no_grad(), static_mode():
                out = model(x, torch.full((x.shape[0],), 7), dict(y))
                counted = count_launches(lambda: model(x, torch.full((x.shape[0],), 7), dict(fresh)), warmup=0)
                again = count_launches(lambda: model(x, torch.full((x.shape[0],), 7), dict(fresh)), warmup=0)
            assert sum(again.syncs.values()) == 0, (take, bound, again.syncs)
            results[bound is None, take] = (out, seen[-1].clone(), sum(counted.syncs.values()))
    for take in ("first", "second"):
        (out_r, mask_r, syncs_r), (out_b, mask_b, syncs_b) = results[True, take], results[False, take]
        assert syncs_r >= 1 and syncs_b == 0, (take, syncs_r, syncs_b)
        assert torch.equal(mask_b, mask_r)
        torch.testing.assert_close(out_b, out_r, rtol=1e-5, atol=1e-6)


def test_a_bound_the_forced_frames_exceed_is_an_error():
    lens = [30, 40, 25]
    model, _ = _sparse_tiny()
    (x, y), _ = _doubletake_calls(model, lens, max(lens))
    attach_doubletake_forcing(model, forced_bound=H)         # the first take forces 2 H in the middle segment
    with pytest.raises(ValueError, match="forced_bound=6"):
        with torch.no_grad():
            model(x, torch.full((3,), 7), dict(y))
    for bad in (-1, 2.5, True, "6"):
        with pytest.raises(TypeError, match="forced_bound"):
            attach_doubletake_forcing(model, forced_bound=bad)


def test_the_priormdm_integration_passes_the_run_bound():
    from smdm_plugin.families.doubletake.model import _ForcingHook, doubletake_forced_bound

    torch.manual_seed(0)
    model = doubleTake_TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
    args = argparse.Namespace(sparse=True, sparse_feature="raw", handshake_size=20, blend_len=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sparsify_priormdm(model, args)
    hooks = [h for h in model._forward_pre_hooks.values() if isinstance(h, _ForcingHook)]
    assert len(hooks) == 1 and hooks[0].bound == doubletake_forced_bound(20, 5) == 40


def test_with_the_run_bound_both_takes_trace_whole():
    """Graph capture (``compile_model``, issue 36): with the run's bound a DoubleTake model's
    sparse calls trace whole (``fullgraph=True``, where a graph break raises) — both takes, early
    and late steps, no recompile within a take — and equal eager; without the bound its calls count
    their forced frames on the host, so the model compiles with graph breaks allowed."""
    import copy

    from smdm_plugin.families.doubletake.model import doubletake_forced_bound
    from smdm_plugin.runtime import compile as C

    pytest.importorskip("torch._dynamo")
    lens = [30, 40, 25]
    model, _ = _sparse_tiny()
    del model.seqTransEncoder.set_plan                    # _sparse_tiny's spy (a copy would share it)
    calls = _doubletake_calls(model, lens, max(lens))
    unbounded = copy.deepcopy(model)
    C.compile_model(unbounded, "default", backend="eager")
    assert not C.compile_setting(unbounded).fullgraph
    attach_doubletake_forcing(model, forced_bound=doubletake_forced_bound(H, BLEND))
    ref = copy.deepcopy(model)
    C.compile_model(model, "default", backend="eager")
    assert C.compile_setting(model).fullgraph
    with torch.no_grad():
        for x, y in calls:
            for step in (9, 8, 1, 0):
                t = torch.full((x.shape[0],), step)
                torch.testing.assert_close(model(x, t, dict(y)), ref(x, t, dict(y)), rtol=1e-5, atol=1e-6)
    s = C.compile_setting(model)
    assert s.compiled_calls > 0 and s.recompiles == 0 and all(model._compiled_call_impl._compiled)
    for bound in (None, doubletake_forced_bound(H, BLEND)):   # priorMDM's class (the DoubleTake family)
        torch.manual_seed(0)
        dt = doubleTake_TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
        sparsify(dt, SparseConfig(feature="raw"))
        attach_doubletake_forcing(dt, forced_bound=bound)
        C.compile_model(dt, "default", backend="eager")
        assert C.compile_setting(dt).fullgraph == (bound is not None)


def _guided_loop(model, x, y, steps=4, change=None):
    """Outputs of ``steps`` sampling calls with two passes each (MDM's guidance: the same ``y``
    tensors, the second pass ``uncond``) at steps 7, 6, ...; ``change(y, step)`` may change ``y``'s
    tensors in place before a step."""
    outs = []
    with torch.no_grad():
        for i in range(steps):
            if change is not None:
                change(y, i)
            t = torch.full((x.shape[0],), 7 - i)
            outs.append(torch.stack([model(x + i, t, dict(y)), model(x + i, t, {**y, "uncond": True})]))
    return outs


@pytest.mark.parametrize("take", ["first", "second"])
def test_a_loop_makes_its_forced_plan_once_and_samples_as_a_plan_per_call(take, monkeypatch):
    """A sampling loop whose calls carry the same tensors (the uniform mask: no dynamic update)
    builds DoubleTake's forced frames and their keyframe plan once for all its steps and guidance
    passes (``call.reuse_for``), and samples exactly as a plan built at every call (the reference:
    nothing kept); an in-place change of ``is_transition`` / ``inpainting_mask`` between steps is
    seen at the next call."""
    import smdm_plugin.adapters.call as call

    lens = [30, 40, 25]
    x, y = _doubletake_calls(None, lens, max(lens))[0 if take == "first" else 1]
    name = "is_transition" if take == "first" else "inpainting_mask"

    def change(y, step):
        if step == 2:                     # the first take: one more forced frame; the second: a shorter ramp
            if take == "first":
                y[name][0, 5] = 1
            else:
                y[name][0, :, :, lens[0] - 2 * H - BLEND] = 1.0

    built, make = [], call._forced_plan
    monkeypatch.setattr(call, "_forced_plan", lambda *a: built.append(1) or make(*a))
    results, kept = {}, call.REUSE_KEEP
    for keep in (kept, 0):
        monkeypatch.setattr(call, "REUSE_KEEP", keep)
        call._REUSED.clear()
        model, seen = _sparse_tiny()
        assert get_state(model).schedule.late_steps == 0
        attach_doubletake_forcing(model, forced_bound=doubletake_forced_bound(H, BLEND))
        built.clear()
        outs = _guided_loop(model, x, {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in y.items()},
                            change=change)
        results[keep] = (outs, len(built), [m.clone() for m in seen[-8:]])
    (reused, n_reused, masks), (rebuilt, n_rebuilt, masks_rebuilt) = results[kept], results[0]
    assert (n_reused, n_rebuilt) == (2, 8)              # once, and once more after the change
    assert not torch.equal(masks[3], masks[4])            # the change reached the plan
    for a, b in zip(masks + reused, masks_rebuilt + rebuilt):
        assert torch.equal(a, b)


def test_a_doubletake_call_launches_what_a_trans_enc_call_launches():
    """Issue 36 (DoubleTake's loop, 0.58x dense on the H200 in bf16): with the run's bound, a guided
    DoubleTake sampling call in a loop (its tensors as the last step's) launches no more kernels than
    MDM trans_enc's on the uniform mask, counted as CUDA runs them at MDM's depth (0.9.3: 66 more
    per call, the forced frames' plan built at every pass), and syncs nothing."""
    from smdm_plugin.core.checks import static_mode
    from smdm_plugin.families.mdm.workload import DOUBLETAKE_HANDSHAKE, _doubletake_class
    from smdm_plugin.reference.simple_diffusion import ClassifierFreeGuidance
    from smdm_plugin.runtime.launches import count_launches
    from smdm_plugin.training.workloads import handshake_frames

    B, N = 8, 196
    lengths = torch.linspace(40, N, B).round().long()
    y = {"lengths": lengths, "mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N),
         "text_embed": torch.randn(1, B, 512)}
    x = torch.randn(B, 263, 1, N)
    for precision in ("fp32", "bf16"):
        counts = {}
        for name, cls in (("trans_enc", TinyMDM), ("doubletake", _doubletake_class())):
            torch.manual_seed(0)
            model = cls(arch="trans_enc", latent_dim=64, ff_size=128, num_layers=8, num_heads=4)
            sparsify(model, SparseConfig(), diffusion=SimpleDiffusion(50))
            yy = dict(y)
            if name == "doubletake":
                attach_doubletake_forcing(model, forced_bound=doubletake_forced_bound(DOUBLETAKE_HANDSHAKE, 0))
                yy["is_transition"] = handshake_frames(lengths, N, DOUBLETAKE_HANDSHAKE)
            guided = ClassifierFreeGuidance(model.eval())

            def sample():
                with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=precision == "bf16"):
                    guided(x + 3, torch.full((B,), 3), yy)
            with static_mode():
                counts[name] = count_launches(sample)
        assert not counts["doubletake"].syncs, counts["doubletake"].syncs
        assert counts["doubletake"].count <= counts["trans_enc"].count, \
            (precision, counts["doubletake"].count, counts["trans_enc"].count)
