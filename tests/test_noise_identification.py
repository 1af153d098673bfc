"""The noise identification (rotcal.noise): its Allan deviation equal to
allantools' on the same series, and the identified IEEE Std 952 terms
within 3 u of the truth of seeded simulations (rotcal.simulate.noise)."""

import math

import allantools
import numpy as np
import polars as pl
import pytest

from rotcal.noise import identify_noise, noise_frame, pooled_avar
from rotcal.noise.model import identify_channel
from rotcal.simulate.noise import NoiseSpec, draw_channels, noise_terms

FS = 1 / 0.06


def test_allan_deviation_equals_allantools():
    """One piece: rotcal's overlapping Allan deviation is allantools' oadev to
    1e-9 relative at every octave tau; two pieces pooled are the pieces'
    second differences together (hand-checked sums)."""
    x = draw_channels(NoiseSpec(white_sd=8.0, flicker_b=1.0, random_walk_k=0.1), 20_000, FS,
                      np.random.default_rng(7), 1)[:, 0]
    ours = pooled_avar([x], FS)
    taus, theirs, _, _ = allantools.oadev(x, rate=FS, data_type="freq", taus=ours.tau_s)
    np.testing.assert_allclose(taus, ours.tau_s, rtol=1e-12)
    np.testing.assert_allclose(ours.adev, theirs, rtol=1e-9, atol=0)
    a, b = x[:7000], x[7000:]
    pooled = pooled_avar([a, b], FS, np.array([4]))
    d = [np.convolve(np.cumsum(np.r_[0.0, p]), [1, 0, 0, 0, -2, 0, 0, 0, 1], "valid") for p in (a, b)]
    assert pooled.avar[0] == pytest.approx(sum(v @ v for v in d) / (2 * 16 * sum(v.size for v in d)), rel=1e-12)


def test_edf_equals_allantools():
    """rotcal's equivalent degrees of freedom (NIST SP 1065 Table 5) are
    allantools' edf_simple for white, flicker and random-walk noise."""
    from rotcal.noise.allan import edf_simple

    for n in (5, 50, 4200, 100_000):
        for m in (1, 2, 4, 64, 1024):
            if n >= 2 * m:
                for alpha in (0, -1, -2):
                    assert edf_simple(n, m, alpha) == pytest.approx(allantools.edf_simple(n, m, alpha), rel=1e-12)


CASES = {
    "white": NoiseSpec(white_sd=8.0),
    "random_walk": NoiseSpec(white_sd=8.0, random_walk_k=0.3),
    "flicker": NoiseSpec(white_sd=8.0, flicker_b=1.5),
    "gauss_markov": NoiseSpec(white_sd=8.0, gauss_markov=((20.0, 2.0),)),
    "ar_0.9": NoiseSpec(white_sd=6.0, ar=(0.9,), ar_sd=4.0),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_identified_terms_within_3u(name):
    """12 rotation-length pieces (4200 samples at 16.7 Hz), 4 seeds: every
    term within 3 u of the truth (white density, B, K, the Gauss-Markov
    term or the AR(1) as one, T_c = -dt / ln phi)."""
    spec = CASES[name]
    truth = noise_terms(spec, FS)
    expected = {"white_density": truth["white_density"], "bias_instability": truth["bias_instability"],
                "random_walk": truth["random_walk"]}
    if truth["gauss_markov"]:
        expected |= {"gauss_markov_tau_s": truth["gauss_markov"][0][0], "gauss_markov_sd": truth["gauss_markov"][0][1]}
    for seed in range(4):
        x = draw_channels(spec, 12 * 4200, FS, np.random.default_rng(100 + seed), 1)[:, 0]
        found = identify_channel("u", [x[i * 4200:(i + 1) * 4200] for i in range(12)], FS, "count")
        terms = {t.term: t for t in found.terms if t.index == 0}
        for term, value in expected.items():
            assert term in terms, (seed, term)
            assert abs(terms[term].value - value) <= 3 * terms[term].u, (seed, term, terms[term], value)


def test_noise_table_of_a_simulated_run():
    """A simulated table recording (white 6, a Gauss-Markov term of 20 s and
    3 counts): the table has the six terms per channel, finite, and the
    white density within 3 u of 6 / sqrt(16.7)."""
    from rotcal.simulate import SimulationSpec, simulate

    sim = simulate(SimulationSpec().with_noise("white_sd=6,gauss_markov=20:3"), 2)
    samples = sim.samples.with_columns(segment=pl.col("plan_segment"))
    theta = samples["angle_deg"].to_numpy()
    rows = []
    for seg in np.unique(samples["segment"].to_numpy()):  # the true sine model as the fit
        mask = samples["segment"].to_numpy() == seg
        z = np.column_stack([np.ones(mask.sum()), np.sin(np.radians(theta[mask])), np.cos(np.radians(theta[mask]))])
        coef = np.linalg.lstsq(z, samples.filter(pl.Series(mask)).select("u", "v", "w").to_numpy(), rcond=None)[0]
        for r, c in enumerate("uvw"):
            rows.append({"segment": int(seg), "channel": c, "status": "ok", "rate_hz": float(samples["rate_hz"][int(np.argmax(mask))]),
                         "rate_fit_hz": float(samples["rate_hz"][int(np.argmax(mask))]), "C": coef[0, r], "A": coef[1, r], "B": coef[2, r]})
    model = identify_noise(samples, pl.DataFrame({"segment": [], "kind": []}), pl.DataFrame(rows), pl.DataFrame({"segment": [], "t_start_ns": [], "t_end_ns": []}), "bit")
    frame = noise_frame(model, "sim")
    assert frame.height == 18 and frame.select(pl.col("value", "u", "dof").is_finite().all()).row(0) == (True,) * 3
    white = frame.filter(term="white_density")
    assert np.all(np.abs(white["value"].to_numpy() - 6 / math.sqrt(FS)) <= 3 * white["u"].to_numpy())


def test_a_run_publishes_the_noise(tmp_path):
    """rotcal run on a simulated recording with a Gauss-Markov wander:
    noise.parquet (schema noise), noise_allan.png, and calibration.json's
    noise holding the same terms as the table."""
    import json

    import pyarrow.parquet as pq
    from typer.testing import CliRunner

    from rotcal.cli import app

    runner = CliRunner()
    assert runner.invoke(app, ["simulate", str(tmp_path / "d"), "--noise", "white_sd=6,gauss_markov=20:3"]).exit_code == 0
    result = runner.invoke(app, ["run", str(tmp_path / "d"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 0, result.output
    table = pq.read_table(tmp_path / "o" / "noise.parquet")
    assert table.schema.metadata[b"rotcal.schema"] == b"noise"
    frame = pl.from_arrow(table)
    assert set(frame["channel"]) == {"u", "v", "w"} and (tmp_path / "o" / "noise_allan.png").stat().st_size > 10_000
    doc = json.loads((tmp_path / "o" / "calibration.json").read_text())
    in_doc = {(c["channel"], t["term"], t["index"]): t["value"] for c in doc["noise"]["channels"] for t in c["terms"]}
    assert in_doc == {(r["channel"], r["term"], r["index"]): r["value"] for r in frame.iter_rows(named=True)}
    white = frame.filter(term="white_density")
    assert np.all(np.abs(white["value"].to_numpy() - 6 / math.sqrt(FS)) <= 3 * white["u"].to_numpy())
