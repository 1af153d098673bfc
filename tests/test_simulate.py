"""The simulator's requests as the user wrote them: a DUT, plan or logger
at the edges of what the defaults show."""

import numpy as np

from rotcal.run import run_dataset
from rotcal.simulate import DutSpec, SimulationSpec, simulate, write_dataset

from testdata import truth_of


def test_simulated_dut_without_full_scale_is_not_clipped(tmp_path):
    """[dut] full_scale = 0 is an output without a limit, as dataset.toml
    (which then has no full_scale) says: the simulator used to clip every
    output to [-1, 0] and the run reported a DUT of 0.07 (m/s^2)/(m/s^2)."""
    dut = DutSpec(sensitivity=1.0, sensitivity_spread=0.002, offset_range=0.5, noise_std=0.005, full_scale=0.0,
                  integer_output=False)
    spec = SimulationSpec(dut=dut, output_unit="m/s^2")
    data = write_dataset(simulate(spec, 1), spec, tmp_path / "d")
    assert "full_scale" not in (data / "dataset.toml").read_text()
    outcome = run_dataset(data, tmp_path / "out")
    truth = truth_of(data)["intrinsic"]
    res = outcome.results[0]
    assert res.rate_hz == 0.0
    assert np.abs((res.value - [truth[p] for p in truth]) / res.std_uncertainty).max() < 4
