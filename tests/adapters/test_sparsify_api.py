"""The library surface of sparsify: config as a dict or a SparseConfig (anything else a TypeError
naming ``config``), set_mean_std only on a sparse model, tensors on the meta device or another
device than the model's are clear errors, and every failure leaves the model as it was."""
import numpy as np
import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM, is_sparse, register_family, set_mean_std, sparsify, unsparsify
from smdm_plugin.adapters.families import family_for, get_family
from smdm_plugin.adapters.family import ModelFamily


def tiny():
    torch.manual_seed(0)
    return TinyMDM(latent_dim=32, ff_size=64, num_layers=1, dropout=0.0, cond_mask_prob=0.0)


def test_a_dict_config_is_converted_and_validated():
    model = sparsify(tiny(), {"reduction": 0.5, "fsq": False})
    assert model._smdm_state.config == SparseConfig(reduction=0.5, fsq=False)
    with pytest.raises(ValueError, match="unknown option 'reductoin'"):
        sparsify(tiny(), {"reductoin": 0.5})
    with pytest.raises(ValueError, match="reduction"):
        sparsify(tiny(), {"reduction": 1.5})


@pytest.mark.parametrize("bad", ["smdm_paper", 0.8, ["reduction", 0.8]])
def test_another_config_type_is_a_type_error_naming_config(bad):
    model = tiny()
    with pytest.raises(TypeError, match="config must be a SparseConfig"):
        sparsify(model, bad)
    assert not is_sparse(model)


def test_set_mean_std_on_a_dense_model_is_a_value_error():
    with pytest.raises(ValueError, match="set_mean_std: TinyMDM is not sparse"):
        set_mean_std(tiny(), np.zeros(263), np.ones(263))
    model = sparsify(tiny(), SparseConfig())
    set_mean_std(model, np.zeros(263), np.ones(263))
    assert torch.equal(model._smdm_state.schedule.std, torch.ones(263))


def test_meta_tensors_are_clear_errors():
    with torch.device("meta"):
        meta_model = TinyMDM(latent_dim=32, ff_size=64, num_layers=1)
    with pytest.raises(ValueError, match="'meta' device"):
        sparsify(meta_model, SparseConfig())
    assert not is_sparse(meta_model)
    model = tiny()
    with pytest.raises(ValueError, match="sparsify: mean is a 'meta' tensor"):
        sparsify(model, SparseConfig(), mean=torch.zeros(263, device="meta"), std=torch.ones(263))
    assert not is_sparse(model) and not hasattr(model, "_smdm_state")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a second device")
def test_statistics_on_another_device_are_an_error():
    with pytest.raises(ValueError, match="std is on cuda"):
        sparsify(tiny(), SparseConfig(), mean=np.zeros(263), std=torch.ones(263, device="cuda"))


def test_unknown_model_names_every_family():
    with pytest.raises(TypeError, match=r"belongs to no registered model family \(doubletake: ") as e:
        sparsify(torch.nn.Linear(3, 3), SparseConfig())
    for name in ("mdm", "motiondiffuse"):   # same priority: in registration (import) order
        assert f"{name}: missing attribute(s)" in str(e.value)
    with pytest.raises(TypeError, match="sparsify: Linear is not a motiondiffuse model"):
        sparsify(torch.nn.Linear(3, 3), SparseConfig(), family="motiondiffuse")


def test_a_new_family_is_one_subclass_and_a_registration():
    """A family reusing MDM's surgery for a model with another class: registered with a higher
    priority, it is chosen over MDM for its models only; its name is unique."""
    mdm = get_family("mdm")

    class Renamed(TinyMDM):
        pass

    class RenamedFamily(type(mdm)):
        name = "renamed-for-test"
        priority = 5
        installed = 0

        def matches(self, model):
            return isinstance(model, Renamed)

        def install(self, model, state):
            RenamedFamily.installed += 1
            super().install(model, state)

    register_family(RenamedFamily())
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_family(RenamedFamily())
        torch.manual_seed(0)
        model = Renamed(latent_dim=32, ff_size=64, num_layers=1)
        assert family_for(model).name == "renamed-for-test" and family_for(tiny()).name == "mdm"
        sparsify(model, SparseConfig())
        assert RenamedFamily.installed == 1 and model._smdm_state.family.name == "renamed-for-test"
        unsparsify(model)
    finally:
        from smdm_plugin.adapters.families import FAMILIES

        FAMILIES.unregister("renamed-for-test")
    with pytest.raises(TypeError, match="must be a ModelFamily"):
        register_family(object())
    assert issubclass(RenamedFamily, ModelFamily)


def test_sampling_under_inference_mode_runs_and_sees_in_place_changes():
    """``torch.inference_mode`` (its tensors keep no version counter: 0.9.3 stopped with
    "Inference tensors do not track version counter" when it reused what it had read of
    ``y['mask']``): an MDM and a MotionDiffuse sampling call under it give what ``no_grad`` gives,
    and an in-place change of the mask / lengths between calls is seen (nothing of an inference
    tensor is kept)."""
    from smdm_plugin.reference.motiondiffuse_denoiser import MotionDiffuseDenoiser

    B, N = 2, 40
    torch.manual_seed(0)
    mdm = sparsify(TinyMDM(latent_dim=32, ff_size=64, num_layers=2, num_heads=4).eval(), SparseConfig())
    md = MotionDiffuseDenoiser(input_feats=263, num_frames=N, latent_dim=32, ff_size=64, num_layers=2,
                               num_heads=4, text_latent_dim=16).eval()
    sparsify(md, SparseConfig(fsq=False), family="motiondiffuse")
    x, t = torch.randn(B, 263, 1, N), torch.tensor([3, 4])
    xf = {"xf_proj": torch.randn(B, 4 * 32), "xf_out": torch.randn(B, 4, 16)}

    def calls(lens):
        mask = (torch.arange(N) < lens[:, None]).view(B, 1, 1, N)
        y = {"mask": mask, "lengths": lens.clone(), "text_embed": torch.zeros(1, B, 512)}
        return mdm(x, t, y), md(x[:, :, 0].transpose(1, 2), t, length=lens.clone(), **xf), y

    with torch.no_grad():
        want = [calls(torch.tensor(lens))[:2] for lens in ([30, 40], [20, 40])]
    with torch.inference_mode():
        lens = torch.tensor([30, 40])
        mask = (torch.arange(N) < lens[:, None]).view(B, 1, 1, N)
        got_mdm, got_md = [], []
        for change in (False, True):
            if change:
                lens[0] = 20
                mask[0, ..., 20:] = False
            y = {"mask": mask, "lengths": lens, "text_embed": torch.zeros(1, B, 512)}
            got_mdm.append(mdm(x, t, y))
            got_md.append(md(x[:, :, 0].transpose(1, 2), t, length=lens, **xf))
    for (w_mdm, w_md), g_mdm, g_md in zip(want, got_mdm, got_md):
        torch.testing.assert_close(g_mdm, w_mdm)
        torch.testing.assert_close(g_md, w_md)
    assert not torch.equal(got_mdm[0], got_mdm[1]) and not torch.equal(got_md[0], got_md[1])
