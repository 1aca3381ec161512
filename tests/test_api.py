"""The public API: ``import mapjoin`` is cheap, every name in ``__all__`` resolves and is documented,
and the package docstring's example runs."""

from __future__ import annotations

import inspect
import subprocess
import sys

import numpy as np
import pytest

import mapjoin


def test_importing_mapjoin_loads_neither_numpy_nor_scipy():
    code = "import sys, mapjoin; print(sorted(m for m in ('numpy', 'scipy', 'yaml', 'click') if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"


@pytest.mark.parametrize("name", mapjoin.__all__)
def test_every_public_name_resolves_and_is_documented(name):
    value = getattr(mapjoin, name)
    if name == "__version__":
        assert isinstance(value, str) and value
    elif callable(value):
        assert inspect.getdoc(value), f"mapjoin.{name} has no docstring"


def test_unknown_names_raise_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        mapjoin.nonsense  # noqa: B018


def test_the_package_example_joins_refines_and_certifies(tmp_path):
    """The docstring's example on simulated maps: the exact join lowers the exact cost of the fast one,
    and Theorem 2's certificate agrees with a brute-force count of the reduced cost's minima."""
    simulation = mapjoin.simulate(6, seed=2)
    path = tmp_path / "maps.yaml"
    mapjoin.write_maps(simulation.maps, str(path), "yaml")
    maps = mapjoin.read_maps(str(path))
    fast = mapjoin.join(maps)
    assert len(fast.report) == len(maps) - 1 and all(record.minima == 1 for record in fast.report)
    exact = mapjoin.join_and_refine(maps)
    from mapjoin.refine import exact_cost

    assert exact.cost <= exact_cost(maps, fast.global_map)
    mapjoin.write_global_map(exact.global_map, str(tmp_path / "exact.csv"))
    assert np.allclose(mapjoin.read_global_map(str(tmp_path / "exact.csv")).features, exact.global_map.features)

    a, c_phi = 5.0, 2.5
    varphi = np.linspace(-np.pi, np.pi, 200001)
    fbar = -a * np.cos(varphi + c_phi) + varphi**2 / 2
    interior = (fbar[1:-1] < fbar[:-2]) & (fbar[1:-1] < fbar[2:])
    assert mapjoin.check_minima(a=a, c_phi=c_phi).minima == int(interior.sum())
