"""The one error system (`jaxrt.errors`): every jaxrt exception is a
`jaxrt.Error` (and keeps its builtin base), every bitmask has one meaning
per bit, and `jaxrt.check` raises the same way for a neighbour list, a
`jaxrt.Pairs` and a domain decomposition's state."""
import types

import numpy as np
import pytest

import jaxrt
from jaxrt import errors
from jaxrt.backends.contract import Capacity
from jaxrt.energy.listfree.lj import InputBit
from jaxrt.pairs.search import ErrorBit
from jaxrt.sim.domains import DomainState, Overflow

BITS = [jaxrt.ErrorCode, ErrorBit, Overflow, InputBit]


def _exceptions():
    import jaxrt.backends.rt.epsilon as epsilon
    import jaxrt.energy as energy
    import jaxrt.sim as sim
    import jaxrt.sim.domains as domains
    return {
        jaxrt.NeighborListError: RuntimeError,
        jaxrt.ListTooLargeError: ValueError,
        jaxrt.PairsError: RuntimeError,
        domains.DomainError: ValueError,
        energy.FusedInputError: ValueError,
        energy.HigherOrderError: TypeError,
        sim.SceneError: ValueError,
        sim.BlowUpError: RuntimeError,
        epsilon.ParticlesTooCloseError: ValueError,
    }


@pytest.mark.parametrize("error, builtin", _exceptions().items(),
                         ids=lambda e: e.__name__)
def test_every_exception_is_a_jaxrt_error_and_keeps_its_builtin_base(
        error, builtin):
    assert issubclass(error, jaxrt.Error) and issubclass(error, builtin)


@pytest.mark.parametrize("bits", BITS, ids=lambda b: b.__name__)
def test_each_bit_has_one_name_and_one_meaning(bits):
    values = [int(b) for b in bits.__members__.values()]
    assert len(values) == len(set(values)), "an alias"
    assert all(v > 0 and v & (v - 1) == 0 for v in values), "one bit each"
    assert issubclass(bits, errors.Bits)


def test_the_lists_bits_fit_jax_mds_uint8():
    assert max(int(b) for b in jaxrt.ErrorCode) < 256


def _list(code, *, radii=False, state=None):
    """A neighbour list as `jaxrt.check` reads it."""
    return types.SimpleNamespace(
        error=types.SimpleNamespace(code=np.asarray(code, np.uint8)),
        cell_list_capacity=Capacity(neighbors=1, radii=radii),
        backend_state=state)


def test_check_names_the_cause_of_a_failed_search():
    failed = jaxrt.ErrorCode.SEARCH_FAILED
    with pytest.raises(jaxrt.NeighborListError, match="radii") as e:
        jaxrt.check(_list(failed, radii=True))
    assert "delaunay" not in str(e.value)
    with pytest.raises(jaxrt.NeighborListError, match="delaunay") as e:
        jaxrt.check(_list(failed, state=object()))
    assert "radii" not in str(e.value)
    jaxrt.check(_list(0))


def test_check_raises_the_same_way_for_lists_pairs_and_domain_states():
    batch = [0, int(jaxrt.ErrorCode.NONFINITE_POSITION)]  # one bad system
    with pytest.raises(jaxrt.NeighborListError, match="NaN or infinite"):
        jaxrt.check(_list(batch))

    def pairs(error):
        z = np.zeros((2, 4), np.int32)
        return jaxrt.Pairs(i=z, j=z, shift=np.zeros((2, 4, 3), np.int32),
                           count=np.zeros(2, np.int32),
                           overflow=np.asarray(error) != 0,
                           error=np.asarray(error, np.int32))

    with pytest.raises(jaxrt.PairsError, match="NaN or infinite"):
        jaxrt.check(pairs([0, int(ErrorBit.NONFINITE_POSITION)]))
    jaxrt.check(pairs([0, 0]))

    def state(error):
        return DomainState(*[None] * 9, error=np.asarray(error, np.int32))

    with pytest.raises(jaxrt.sim.domains.DomainError,
                       match=r"HALO on device\(s\) \[1\]"):
        jaxrt.check(state([0, int(Overflow.HALO)]))
    jaxrt.check(state([0, 0]))
    with pytest.raises(TypeError, match="no jaxrt error bits"):
        jaxrt.check(object())


def test_raise_for_joins_the_messages_of_the_bits_set():
    table = {1: "one", 2: "two", 4: "four"}
    with pytest.raises(jaxrt.PairsError, match="^x: one; four$"):
        errors.raise_for(5, table, jaxrt.PairsError, "x: ")
    errors.raise_for(8, table, jaxrt.PairsError, "x: ")  # no bit of the table
