"""Extension points are registries: a new selector or attention backend is one registration, and
the config, the selection entry points and the keyframe transformer accept it at once."""
import pytest
import torch

from smdm_plugin import SparseConfig, register_backend, register_selector, select_keyframes
from smdm_plugin.core.keyframe_transformer import KeyframeTransformer
from smdm_plugin.core import attention_backends as ab
from smdm_plugin.core.checks import static_mode
from smdm_plugin.core.schedule import MaskSchedule
from smdm_plugin.core.selection import SELECTORS


def last_frames(features, lengths, counts, generator, forced, active):
    """A toy selector: frame 0 and the last ``count - 1`` valid frames."""
    idx = torch.arange(features.shape[1])[None]
    L, k = lengths[:, None], counts[:, None]
    return (idx == 0) | ((idx < L) & (idx >= L - (k - 1)))


@pytest.fixture
def toy_selector():
    register_selector("last", last_frames)
    yield
    SELECTORS.unregister("last")


def test_a_registered_selector_is_a_config_value_and_runs_with_forced_frames(toy_selector):
    assert SparseConfig(selector="last").selector == "last"
    x = torch.randn(2, 10, 3)
    lengths = torch.tensor([10, 6])
    forced = torch.zeros(2, 10, dtype=torch.bool)
    forced[0, 3] = True
    mask = select_keyframes(x, lengths, reduction=0.5, method="last", forced=forced)
    # sample 0: K=5, one forced interior frame -> 4 of its own: 0, 7, 8, 9; plus forced 3
    assert mask[0].nonzero().flatten().tolist() == [0, 3, 7, 8, 9]
    assert mask[1].nonzero().flatten().tolist() == [0, 4, 5]
    sched = MaskSchedule(SparseConfig(selector="last", reduction=0.5, mask_noise=0.0, feature="raw"))
    assert torch.equal(sched.training_mask(x, lengths), select_keyframes(x, lengths, 0.5, "last"))
    with pytest.raises(ValueError, match="active rows are not supported by method='last'"):
        select_keyframes(x, lengths, 0.5, "last", active=torch.ones(2, dtype=torch.bool))


def test_an_unregistered_selector_is_not_a_config_value():
    with pytest.raises(ValueError, match="SparseConfig.selector='last'"):
        SparseConfig(selector="last")


def test_backend_capabilities_decide_the_dispatch():
    calls = []

    def recording(*args, **kwargs):
        calls.append(1)
        return ab.compact_backend(*args, **kwargs)

    register_backend("_dynamic", recording, static_shapes=False)
    register_backend("_picky", recording, supports=lambda inner: False)
    try:
        with pytest.raises(ValueError, match="'_picky' is already registered"):
            register_backend("_picky", recording)                 # no silent replacement
        assert ab.BACKENDS.get("_picky").supports(None) is False
        register_backend("_picky", recording, supports=lambda inner: False, replace=True)
        assert SparseConfig(attention_backend="_dynamic").attention_backend == "_dynamic"
        cpu = torch.device("cpu")
        assert ab.resolve_backend_name("_dynamic", cpu) == "_dynamic"
        with static_mode():                                       # dynamic shapes: not on the static path
            assert ab.resolve_backend_name("_dynamic", cpu) == ab.FALLBACK
        layer = torch.nn.TransformerEncoderLayer(16, 2, 32, dropout=0.0)
        tr = KeyframeTransformer(torch.nn.TransformerEncoder(layer, 1, enable_nested_tensor=False),
                                 backend="_picky").eval()
        tr.set_keyframes(torch.ones(2, 5, dtype=torch.bool))
        with torch.no_grad(), pytest.warns(RuntimeWarning, match="'_picky' falls back to 'compact'"):
            tr(torch.randn(5, 2, 16))
        assert calls == []                                        # it cannot run these layers
        tr.backend = "_dynamic"
        with torch.no_grad():
            tr(torch.randn(5, 2, 16))
        assert calls == [1]
    finally:
        ab.BACKENDS.unregister("_dynamic")
        ab.BACKENDS.unregister("_picky")
        ab._WARNED.clear()
