import numpy as np
import pytest

from minority.gns.graph import radius_graph


def _all_pairs(pos, r):
    d2 = ((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1)
    recv, send = np.nonzero(d2 <= r * r)
    keep = recv != send
    return set(zip(send[keep].tolist(), recv[keep].tolist(), strict=False))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cell_list_equals_all_pairs(seed):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 0.2, (700, 3)) * np.array([1.0, 0.5, 2.0])
    r = 0.029
    s, rv = radius_graph(pos, r)
    assert set(zip(s.tolist(), rv.tolist(), strict=False)) == _all_pairs(pos, r)
    assert len(s) == len(set(zip(s.tolist(), rv.tolist(), strict=False)))  # no duplicate edges
    assert np.all(np.diff(rv) >= 0)


def test_lattice_has_no_neighbour_cap():
    s = 0.016
    g = np.stack(np.meshgrid(*[np.arange(8) * s] * 3, indexing="ij"), -1).reshape(-1, 3)
    g = np.concatenate([g, g + 1e-4])  # doubled lattice: twice the neighbours
    snd, rcv = radius_graph(g, 0.029)
    counts = np.bincount(rcv, minlength=len(g))
    assert counts.max() == 53  # interior: 26 lattice neighbours twice, plus the twin
    assert set(zip(snd.tolist(), rcv.tolist(), strict=False)) == _all_pairs(g, 0.029)


def test_edge_cases():
    s, r = radius_graph(np.zeros((0, 3)), 0.1)
    assert len(s) == len(r) == 0
    s, r = radius_graph(np.zeros((3, 3)), 0.1)  # coincident points are neighbours
    assert len(s) == 6
    with pytest.raises(ValueError, match="non-finite"):
        radius_graph(np.array([[0.0, 0, 0], [np.nan, 0, 0]]), 0.1)
