"""The evaluator's R-precision reacts to the order of a motion and to its caption: the recipe of
``smdm evaluator train`` (small sizes, few epochs) on captioned motions whose caption names the order
of two phases ("a person walks then jumps"; every ordered pair of four phases), checked with the same
:func:`~smdm_plugin.metrics.evaluator.check.retrieval_check` that ``smdm evaluator train`` prints
(paired drops of R-precision top-3 for time-reversed motion and for swapped captions). A recipe, or a
check, that stops seeing order or captions fails here in seconds; the full check on real motion with
several seeds is ``scripts/evaluator_seeds.py`` (its table: docs/evaluation.md)."""
import dataclasses

import numpy as np
import pytest

from smdm_plugin.io.captions import Caption
from smdm_plugin.metrics.evaluator.check import retrieval_check
from smdm_plugin.metrics.evaluator.data import CaptionedMotions
from smdm_plugin.metrics.evaluator.seeds import SeedRow, SeedTable, load_seed_table, recipe_of
from smdm_plugin.metrics.evaluator.train import DEFAULT_RECIPE, TrainSettings, build_evaluator, train_evaluator

from helpers.paths import ROOT

PHASES = ("walk", "jump", "kick", "wave")
D = 16
SMALL = dict(dim_word=16, dim_movement_hidden=32, dim_movement_latent=32, dim_motion_hidden=32, dim_text_hidden=32,
             dim_coemb=16)


def _phases(per: int, seed: int) -> CaptionedMotions:
    """``per`` motions of every ordered pair (a, b) of :data:`PHASES`, a != b: phase a (24-40 frames:
    a bump with a ramp in its own 3 features) then phase b, noise elsewhere; caption "a person a then b"."""
    rng = np.random.default_rng(seed)
    ids, motions, caps = [], [], []
    for a in range(len(PHASES)):
        for b in range(len(PHASES)):
            if a == b:
                continue
            for k in range(per):
                parts = []
                for p in (a, b):
                    n = int(rng.integers(24, 41))
                    t = np.linspace(0.0, 1.0, n)[:, None]
                    x = 0.3 * rng.standard_normal((n, D))
                    x[:, 3 * p:3 * p + 3] += np.sin(np.pi * t) * np.array([2.0, 1.0, -1.5]) + t * np.array([0.0, 1.5, 0.0])
                    parts.append(x)
                ids.append(f"{PHASES[a]}-{PHASES[b]}-{k}")
                motions.append(np.concatenate(parts).astype(np.float32))
                caps.append([Caption(f"a person {PHASES[a]}s then {PHASES[b]}s",
                                     ["a/DET", "person/NOUN", f"{PHASES[a]}/VERB", "then/ADV", f"{PHASES[b]}/VERB"])])
    every = np.concatenate(motions)
    return CaptionedMotions(ids, motions, caps, every.mean(0), every.std(0) + 1e-3, representation="joints66")


def test_recipe_r_precision_falls_for_reversed_motion_and_swapped_captions():
    train, val, test = _phases(8, 0), _phases(2, 1), _phases(3, 2)   # 96, 24, 36 motions (a pool of 32)
    for d in (val, test):
        d.mean, d.std = train.mean, train.std
    default = TrainSettings(recipe=DEFAULT_RECIPE)
    s = dataclasses.replace(default, sizes=dict(SMALL), ae_epochs=10, epochs=40, lr=1e-3, ae_lr=1e-3, ae_window=32)
    ev = build_evaluator(train, s)
    train_evaluator(ev, train, val, s)
    c = retrieval_check(ev, test, replications=10, seed=0)
    assert c.pool == 32 and c.top3[0] > 0.6, c.line()                 # it learned the captions (chance 0.094)
    assert c.sees_order() and c.drop_reversed_top3[0] > 0.3, c.line()  # played backwards: "b then a"
    assert c.sees_captions() and c.drop_swapped_top3[0] > 0.3, c.line()


def test_the_packaged_seed_table_is_the_docs_table_of_the_default_recipe():
    """smdm evaluator train prints the packaged table; docs/evaluation.md shows the same one, measured
    with the default recipe, on >= 3 seeds, each of which sees order and captions."""
    table = load_seed_table()
    assert table is not None and len(table.rows) >= 3
    assert table.settings == recipe_of(TrainSettings(recipe=DEFAULT_RECIPE).to_dict())
    assert all(r.sees_order() and r.sees_captions() for r in table.rows)
    page = (ROOT / "docs" / "evaluation.md").read_text()
    assert table.markdown() in page and table.spread_markdown() in page
    from smdm_plugin.apps.evaluator import recipe_spread

    default = TrainSettings(recipe=DEFAULT_RECIPE)
    assert table.spread_markdown() in recipe_spread(default, None)           # smdm evaluator train's summary
    assert recipe_spread(dataclasses.replace(default, epochs=3), None) == ""  # another recipe: not its spread
    assert recipe_spread(default, "glove") == ""


def test_seed_table_file_round_trip(tmp_path):
    from smdm_plugin.metrics.evaluator.seeds import save_seed_table

    check = {"top1": [0.2, 0.02], "top3": [0.4, 0.02], "reversed_top3": [0.3, 0.02], "swapped_top3": [0.1, 0.02],
             "drop_reversed_top1": [0.1, 0.02], "drop_reversed_top3": [0.1, 0.03], "drop_swapped_top3": [0.3, 0.4],
             "fid_floor": [1.8, 0.3], "replications": 20, "pool": 32}
    t = SeedTable("toy", {"recipe": "t2m"}, 20, [SeedRow(0, 0.2, 0.4, check, 30, 100.0)])
    path = save_seed_table(t, str(tmp_path / "s.json"))
    again = load_seed_table(path)
    assert again == t and again.rows[0].sees_order() and not again.rows[0].sees_captions()
    assert "0 of 1" in t.spread_markdown() and "| 0 | 0.200 | 0.400 |" in t.markdown()
    (tmp_path / "s.json").write_text("[]")
    with pytest.raises(ValueError, match="s.json"):
        load_seed_table(path)


def test_evaluator_train_prints_and_saves_its_check(tmp_path, capsys):
    """smdm evaluator train ends with the R-precision check on its test split (in evaluator.json and
    metrics.json, printed, a warning when a drop is not clear of 0); the reversed negatives belong to the
    t2m recipe only (exit 2 before anything is written)."""
    import json

    from smdm_plugin.apps.cli import main as smdm

    out = tmp_path / "ev"
    assert smdm(["evaluator", "train", "--out", str(out), "--epochs", "1", "--ae-epochs", "1", "--hidden", "16",
                 "--dim", "8", "--no-progress", "--threads", "1"]) == 0
    captured = capsys.readouterr()
    assert "replications of smdm eval's protocol" in captured.out and "time-reversed" in captured.out
    info = json.loads((out / "evaluator.json").read_text())
    check = info["retrieval_check"]
    assert check["split"] == "test" and check["replications"] == 20 and len(check["drop_reversed_top3"]) == 2
    assert info["train_settings"]["reversed_negatives"] is True and info["train_settings"]["select"] == "val_loss"
    assert json.loads((out / "metrics.json").read_text())["retrieval_check"] == check
    blind = not (check["drop_reversed_top3"][0] - check["drop_reversed_top3"][1] > 0
                 and check["drop_swapped_top3"][0] - check["drop_swapped_top3"][1] > 0)
    assert ("warning: this evaluator's R-precision does not fall clearly" in captured.err) == blind
    for t2m_only, name in ((["--reversed-negatives"], "--reversed-negatives"), (["--margin", "5"], "--margin"),
                           (["--ae-epochs", "3"], "--ae-epochs")):    # 0.10.5 ignored the last two
        with pytest.raises(SystemExit) as e:
            smdm(["evaluator", "train", "--out", str(tmp_path / "c"), "--recipe", "contrastive", *t2m_only])
        assert e.value.code == 2 and f"argument {name}: only with --recipe t2m" in capsys.readouterr().err
        assert not (tmp_path / "c").exists()
