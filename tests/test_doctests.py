"""The runnable examples in the public core's docstrings run and print what they say.

Proof kind: each example is an executable statement of a property (a noise-free pose recovered
exactly, Chen eq. 22 read off the covariance, the ideal forward model equal to the sweep angles),
run by the standard library's doctest on the module itself.
"""
import doctest
import importlib

import pytest

#: module → whether it must hold examples (the public core documented with one each:
#: solve_pnp, pose_dop, measure, and optimize_layout / solve in layoutkit.optimize.solver)
MODULES = {"layoutkit.pnp": True, "layoutkit.dop": True, "layoutkit.lighthouse": True,
           "layoutkit.optimize.solver": True}


@pytest.mark.parametrize("name", sorted(MODULES))
def test_docstring_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert res.failed == 0, f"{name}: {res.failed} of {res.attempted} doctest examples failed (details above)"
    if MODULES[name]:
        assert res.attempted > 0, f"{name}: no runnable example"
