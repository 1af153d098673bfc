"""What a batch worker and ``rotcal run`` import: the diagnosis's
statistics come from scipy.special (scipy.stats costs 0.32 s of CPU to
import, in every worker), with the same values to the bit as the
scipy.stats functions they stand for; the combined parts' lists are renamed
without pyarrow.compute. The batch process plans a run without loading
numpy, polars, pyarrow or scipy, so its pool starts sooner."""

import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from rotcal.diagnose.clipping import stuck_values
from rotcal.diagnose.scans import normal_p


def test_a_worker_job_leaves_out_scipy_stats_and_pyarrow_compute(make_dataset, tmp_path):
    """A pool worker's imports (``JOB_MODULES``, the static diagnosis's
    modules too) and a whole job on a default-plan dataset load neither
    (each 0.16 to 0.32 s of CPU, paid again by every worker). scipy.optimize
    is loaded: the noise model's fit (``rotcal.noise.model``) uses its
    bounded least squares and Nelder-Mead, once a worker."""
    code = ("import importlib, sys\n"
            "from rotcal.batch.jobs import JOB_MODULES, Job, run_job\n"
            "from rotcal.config import RunConfig\n"
            "for name in JOB_MODULES + ('rotcal.diagnose.static', 'rotcal.report.static_diagnosis'):\n"
            "    importlib.import_module(name)\n"
            f"result = run_job(Job('d', {str(make_dataset(1))!r}, {str(tmp_path / 'work')!r}, RunConfig(), {{}}))\n"
            "print(result.status, sorted(m for m in ('scipy.stats', 'pyarrow.compute') if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "ok []"


def test_the_batch_process_plans_without_numpy_polars_pyarrow_or_scipy(make_dataset, tmp_path):
    """What ``rotcal batch`` imports before its pool starts, and what planning
    a dataset (its captures found and hashed) loads: none of the four (0.4 s
    of the batch process's imports, while the workers start on both cores)."""
    shutil.copytree(make_dataset(1), tmp_path / "root" / "dut")
    code = ("import json, sys\n"
            "from pathlib import Path\n"
            "import rotcal.cli, rotcal.batch.runner\n"
            "from rotcal.batch.manifest import Manifest\n"
            "from rotcal.batch.plan import config_json, discover, plan_dataset\n"
            "from rotcal.config import RunConfig\n"
            f"root, tmp = Path({str(tmp_path / 'root')!r}), Path({str(tmp_path)!r})\n"
            "config, manifest = RunConfig(), Manifest(tmp / 'manifest.sqlite')\n"
            "plans = [plan_dataset(f, root, config, manifest, config_json(config)) for f in discover(root, tmp / 'out')]\n"
            "print([(p.refusal, len(json.loads(p.inputs))) for p in plans], "
            "sorted(m for m in ('numpy', 'polars', 'pyarrow', 'scipy') if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "[(None, 16)] []"


@pytest.mark.parametrize("draw", ["normal", "t5", "exponential", "quantised"])
def test_normal_p_is_scipy_normaltest_to_the_bit(draw):
    rng = np.random.default_rng(["normal", "t5", "exponential", "quantised"].index(draw))
    for n in (200, 1_000, 54_000):
        x = {"normal": rng.normal(size=n), "t5": rng.standard_t(5, size=n), "exponential": rng.exponential(size=n),
             "quantised": np.round(3 * rng.normal(size=n))}[draw] * 2.5e-3 + 512.0
        assert normal_p(x) == stats.normaltest(x).pvalue


def test_normal_p_of_a_ramp():
    # 300 equally spaced values: no skew (Z_skew = 0), b2 = 1.8 (a uniform's
    # kurtosis): K^2 = Z_kurt^2 alone, and scipy's value printed here
    assert normal_p(np.arange(300.0)) == pytest.approx(4.083676596190384e-36, rel=1e-14)


def test_stuck_value_p_is_the_binomial_tail():
    # 40 samples at the extreme 2047 and 25 one quantum inside it: P(X >= 40), X ~ B(65, 1/2), doubled
    y = np.zeros((1000, 3))
    y[:40, 0], y[40:65, 0] = 2047.0, 2046.0
    y[65:, 0] = np.arange(935) % 2000 - 1000.0
    high = next(s for s in stuck_values(y, 1.0) if s.channel == "u" and s.side == "high")
    assert (high.count, high.neighbour_count) == (40, 25)
    assert high.p_value == 2 * stats.binom.sf(39, 65, 0.5)
