"""Coarse-graining MPM runs to the GNS spacing: a group's mean or one sampled member."""

from pathlib import Path

import numpy as np
import pytest

from minority.gns.dataset import DatasetError, coarse_grain
from minority.gns.metrics import deposit
from minority.gns.sweep import SweepError, load_config, plan

CONFIGS = Path(__file__).resolve().parent.parent / "gns" / "configs"


def lattice(shape, spacing):
    idx = np.stack(np.meshgrid(*(np.arange(k) for k in shape), indexing="ij"), -1)
    return (idx.reshape(-1, 3) + 0.5) * spacing


def test_sample_starts_on_the_mean_and_moves_as_one_member_of_its_group():
    fine = 0.5  # m
    x0 = lattice((4, 2, 3), fine)  # two whole 2x2x2 cubes and two half ones
    rng = np.random.default_rng(1)
    run = np.stack([x0, x0 + rng.normal(0, 0.1, x0.shape), x0 + rng.normal(0, 0.3, x0.shape)])
    mean = coarse_grain(run, fine, 2)
    got = coarse_grain(run, fine, 2, "sample", seed=3)
    assert got.shape == mean.shape == (3, 4, 3)
    np.testing.assert_allclose(got[0], mean[0], atol=1e-12)
    cube = np.floor(x0 / (2 * fine)).astype(int)
    for k, key in enumerate([(0, 0, 0), (0, 0, 1), (1, 0, 0), (1, 0, 1)]):
        members = np.flatnonzero((cube == key).all(axis=1))
        offset = x0[members] - mean[0, k]
        # the same member in every frame, shifted by its offset at frame 0
        hit = [m for j, m in enumerate(members)
               if np.allclose(got[:, k], run[:, m] - offset[j], atol=1e-12)]
        assert len(hit) == 1, key
    np.testing.assert_array_equal(got, coarse_grain(run, fine, 2, "sample", seed=3))
    picks = {tuple(coarse_grain(run, fine, 2, "sample", seed=s)[1].ravel()) for s in range(8)}
    assert len(picks) > 1  # the seed chooses the members
    assert coarse_grain(run, 1.0, 1, "sample") is run
    with pytest.raises(DatasetError, match="'median'"):
        coarse_grain(run, fine, 2, "median")


def test_a_sampled_front_keeps_the_spread_a_mean_loses():
    """A body whose particles scatter about a uniform stretch: group means shrink the scatter,
    so their front (a high quantile) trails the run's; sampled members keep it."""
    fine = 0.01
    x0 = lattice((40, 8, 8), fine)
    rng = np.random.default_rng(0)
    last = x0 * [2.0, 1.0, 1.0] + rng.normal(0, 0.05, x0.shape)
    run = np.stack([x0, last])
    full = deposit(run).runout_m
    mean_gap = full - deposit(coarse_grain(run, fine, 2)).runout_m
    sample_gap = full - np.mean([deposit(coarse_grain(run, fine, 2, "sample", seed=s)).runout_m
                                 for s in range(10)])
    assert mean_gap > 0.03  # the scatter is 0.05 m; a mean of 8 has 0.018 m
    assert abs(sample_gap) < 0.3 * mean_gap


def test_the_sample_config_is_the_long_sweep_with_sampled_members(tmp_path):
    sample = load_config(CONFIGS / "column_sweep_cg2_sample.toml")
    long = load_config(CONFIGS / "column_sweep_cg2_long.toml")
    assert (sample.coarse_grain_method, long.coarse_grain_method) == ("sample", "mean")
    assert plan(sample) == plan(long)  # the same scenes: the same MPM runs
    bad = tmp_path / "bad.toml"
    bad.write_text(f'extends = "{CONFIGS / "column_sweep_cg2.toml"}"\n'
                   'coarse_grain_method = "median"\n')
    with pytest.raises(SweepError, match="coarse_grain_method 'median'"):
        load_config(bad)


def test_the_wide_config_adds_wide_columns_far_from_the_side_walls():
    """Every scene of the sample sweep stays (same runs); the added ones are wider than any
    base channel, so their middle is further from a side wall than the model's receptive
    field (5 message-passing steps of 0.029 m), as in wide_10x."""
    sample = plan(load_config(CONFIGS / "column_sweep_cg2_sample.toml"))
    wide_cfg = load_config(CONFIGS / "column_sweep_cg2_wide.toml")
    wide = plan(wide_cfg)
    assert wide_cfg.coarse_grain_method == "sample"
    names = {p.name for p in sample}
    assert [p for p in wide if p.name in names] == sample
    added = [p for p in wide if p.name not in names]
    assert sorted(p.split for p in added) == ["train"] * 12 + ["valid"] * 2
    base_width = max(p.width_m for p in sample if p.split != "test")
    assert base_width / 2 < 5 * wide_cfg.connectivity_radius_m
    for p in added:
        assert p.width_m / 2 > 5 * wide_cfg.connectivity_radius_m, p
        assert 800 <= p.particles <= 3000, p


def test_the_tall_config_adds_wide_columns_taller_than_the_wide_ones():
    """The wide sweep stays (same runs); the added columns are as far from a side wall in
    their middle and taller than every wide one, up to wide_10x's height."""
    wide = plan(load_config(CONFIGS / "column_sweep_cg2_wide.toml"))
    tall_cfg = load_config(CONFIGS / "column_sweep_cg2_tall.toml")
    tall = plan(tall_cfg)
    names = {p.name for p in wide}
    assert [p for p in tall if p.name in names] == wide
    added = [p for p in tall if p.name not in names]
    assert sorted(p.split for p in added) == ["train"] * 10 + ["valid"] * 2
    sample = {p.name for p in plan(load_config(CONFIGS / "column_sweep_cg2_sample.toml"))}
    wide_heights = [p.height_m for p in wide if p.name not in sample]
    train_added = [p for p in added if p.split == "train"]
    assert max(p.height_m for p in train_added) == 0.352 > max(wide_heights)
    assert sum(p.height_m > max(wide_heights) for p in train_added) >= 5
    for p in added:
        assert p.width_m / 2 > 5 * tall_cfg.connectivity_radius_m, p
        assert 800 <= p.particles <= 3000, p
