"""benchmarks/pairs.py's batch scene and its pair-set check (the check that
turns an nvalchemiops row into an error): the check against a float64
brute force over a flat batch, and that it catches a missing pair, a wrong
shift and a duplicate while excusing only pairs at the cutoff."""
import itertools
import sys

import numpy as np
import pytest

from benchmarks import pairs as bench


def brute_batch(pos, n_node, cells, cutoff):
    """Full (i, j, shift) lists of every system, float64, global indices;
    shifts up to +-2 cover cells longer than cutoff / 2."""
    out_i, out_j, out_s = [], [], []
    start = 0
    shifts = np.array(list(itertools.product(range(-2, 3), repeat=3)))
    for m, h in zip(n_node, cells):
        x = pos[start:start + m]
        d = (x[None, :, None] - x[:, None, None]
             + (shifts @ h)[None, None])  # (i, j, shift, 3)
        r = np.linalg.norm(d, axis=-1)
        i, j, s = np.nonzero(r < cutoff)
        keep = ~((i == j) & np.all(shifts[s] == 0, axis=1))
        out_i.append(i[keep] + start)
        out_j.append(j[keep] + start)
        out_s.append(shifts[s[keep]])
        start += m
    return (np.concatenate(out_i), np.concatenate(out_j),
            np.concatenate(out_s))


@pytest.fixture(scope="module")
def batch():
    pos, n_node, cells = bench.batch_scene(3, 32)
    system_of = np.repeat(np.arange(len(n_node)), n_node)
    return pos, n_node, cells, system_of


def test_batch_scene_is_periodic_fcc_of_the_requested_size(batch):
    pos, n_node, cells, _ = batch
    assert pos.shape == (96, 3) and n_node.tolist() == [32] * 3
    assert cells.shape == (3, 3, 3)
    assert bench.fcc_reps(32) == (2, 2, 2)
    assert bench.fcc_reps(128) == (4, 4, 2)
    with pytest.raises(ValueError, match="multiple of 4"):
        bench.parse_batch("8x30")
    with pytest.raises(ValueError, match="GxM"):
        bench.parse_batch("8by32")


def test_check_agrees_with_brute_force_and_catches_differences(batch):
    import jax
    import jaxrt
    pos, n_node, cells, system_of = batch
    ref = brute_batch(pos, n_node, cells, bench.CUTOFF)
    with jax.enable_x64(True):  # float64 as the brute force
        got = jaxrt.pairs_batch(pos, n_node, bench.CUTOFF, cell=cells)
    k = int(got.count)
    got = (np.asarray(got.i)[:k], np.asarray(got.j)[:k],
           np.asarray(got.shift)[:k])
    tol = bench.pair_tolerance("float64", pos, cells)

    def check(a, b):
        return bench.compare_pairs(a, b, pos, cells, system_of,
                                   bench.CUTOFF, tol)

    assert check(got, ref) == {"same_pairs": True, "boundary": 0,
                               "reason": None}
    dropped = tuple(v[1:] for v in got)
    verdict = check(dropped, ref)
    assert not verdict["same_pairs"] and "1 pairs differ" in verdict["reason"]
    wrong = (got[0], got[1], got[2].copy())
    wrong[2][0, 0] += 1
    assert not check(wrong, ref)["same_pairs"]
    doubled = tuple(np.concatenate([v, v[:1]]) for v in got)
    assert "duplicate" in check(doubled, ref)["reason"]
    # A pair missing from one list is excused only at the cutoff: move the
    # cutoff onto the dropped pair's length.
    i, j, s = (v[0] for v in got)
    r0 = np.linalg.norm(pos[j] - pos[i] + s @ cells[system_of[i]])
    verdict = bench.compare_pairs(dropped, got, pos, cells, system_of,
                                  float(r0), tol)
    assert verdict == {"same_pairs": True, "boundary": 1, "reason": None}


def test_matrix_output_unrolls_rows_and_rejects_overflow():
    nm = np.array([[1, 2, 9], [0, 9, 9]])
    nn = np.array([2, 1])
    sh = np.arange(18).reshape(2, 3, 3)
    i, j, s = bench.matrix_pairs((nm, nn, sh))
    assert i.tolist() == [0, 0, 1] and j.tolist() == [1, 2, 0]
    assert s.tolist() == [sh[0, 0].tolist(), sh[0, 1].tolist(),
                          sh[1, 0].tolist()]
    with pytest.raises(RuntimeError, match="max_neighbors"):
        bench.matrix_pairs((nm, np.array([4, 1]), sh))


def test_nvalchemiops_rows_are_skipped_without_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "nvalchemiops", None)
    job = {"method": bench.NVAL_JIT, "system": "8x32", "N": 256,
           "dtype": "float32", "repeats": 1, "warmup": 1, "target_s": None,
           "max_repeats": 1}
    row = bench.run_row(job)
    assert row["status"] == "skipped" and "nvalchemiops" in row["failed"]


def test_nvalchemiops_jit_row_matches_jaxrt_where_installed():
    pytest.importorskip("nvalchemiops.jax.neighbors")
    job = {"method": bench.NVAL_JIT, "system": "diamond", "N": 1000,
           "dtype": "float32", "repeats": 1, "warmup": 1, "target_s": None,
           "max_repeats": 1}
    row = bench.run_row(job)
    assert row.get("status", "ok") == "ok", row
    assert row["same_pairs"] and row["pairs"] == 28000
