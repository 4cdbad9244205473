"""Shared test settings: one torch thread (measured 5-17x faster than 2 on this 2-core VM for
small tensors) and a per-session dataset cache."""

import importlib.util
import os
from pathlib import Path
from types import ModuleType

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="session")
def _cache_dir(tmp_path_factory):
    if "ICPBENCH_CACHE" not in os.environ:
        os.environ["ICPBENCH_CACHE"] = str(tmp_path_factory.mktemp("icpbench-cache"))
    yield


@pytest.fixture
def reuse_radii(monkeypatch):
    """Records the ``reuse`` radius (metres) of every ICP correspondence cache built while the
    test runs (``icpbench.targets.icp._Correspondences``): one entry per ICP call."""
    import icpbench.targets.icp as icp_mod

    seen: list[float] = []
    real = icp_mod._Correspondences

    class Spy(real):
        def __init__(self, *args, reuse=0.0, **kw):
            seen.append(reuse)
            super().__init__(*args, reuse=reuse, **kw)

    monkeypatch.setattr(icp_mod, "_Correspondences", Spy)
    return seen


@pytest.fixture
def user_error():
    """A checker of a CLI result that is a user error: exit status 2, ``needle`` in the output,
    no traceback."""

    def check(res, needle: str) -> None:
        assert res.exit_code == 2, res.output
        assert needle in res.output, res.output
        assert "Traceback" not in res.output

    return check


@pytest.fixture(scope="module")
def scene_pair():
    """Two 800-point scans of one synthetic scene (8,000-point map): a small batch to attack."""
    from icpbench.core.types import Batch
    from icpbench.datasets.synthetic_scene import scene_sample

    return Batch.from_samples([scene_sample(n_scan=800, n_map=8000, seed=s, scene_seed=1)
                               for s in (3, 4)])


@pytest.fixture(scope="session")
def load_script():
    """A loader of ``scripts/<name>.py`` as a module (scripts are not a package), for tests of
    their functions: ``load_script("frontier")``."""
    return _load_script


def _load_script(name: str) -> ModuleType:
    path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"{name}_script", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def answers_as_target():
    """``check(target, batch, budget_m, **ensemble_settings)``: the ensemble run twice, its
    queries answered by the target and by ``target.exact_replica()``; asserts that every
    member's error (to 1e-9 m) and the query counts are the same."""
    import numpy as np

    from icpbench.attacks.ensemble import EnsembleAttack, column
    from icpbench.targets.oracle import QueryOracle

    def check(target, batch, budget_m: float, **settings) -> None:
        ens = EnsembleAttack(**settings)
        by_target = QueryOracle.prepared(target, batch)
        answered = QueryOracle.prepared(target, batch, answer_with=target.exact_replica())
        a = ens.run(batch, budget_m, surrogate=None, generator=0, oracle=by_target)
        b = ens.run(batch, budget_m, surrogate=None, generator=0, oracle=answered)
        for m in settings["members"].split(","):
            np.testing.assert_allclose(b.extra[column(m)].numpy(), a.extra[column(m)].numpy(),
                                       rtol=0, atol=1e-9)
        np.testing.assert_array_equal(answered.queries, by_target.queries)

    return check
