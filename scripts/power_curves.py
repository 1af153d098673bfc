"""Power curves of the diagnosis against the best test (issue 15 item 4).

For every catalogue effect, simulated on the default plan (a labelled table
run) at sizes from well below the catalogue's range (``sizes``) to its upper
end: the fraction of datasets in which rotcal's diagnosis (the default
configuration) names the effect, and the fraction in which the generalized
likelihood-ratio test of the true nested model (``rotcal.diagnose.glr``:
the baseline plus the effect's exact extension, on its true axis or channel)
rejects the baseline, both at rotcal's false-alarm rate per effect test
(``[diagnosis] false_alarm``). A probit in log size fitted to each gives the
sizes at 50 % and 80 % power. Clean datasets calibrate both tests.

    python scripts/power_curves.py [--seeds 8] [--points 7] [--clean 24] [--workers 2] [--quick]
    python scripts/power_curves.py --noise mix [--seeds 4] [--points 5] [--clean 4] ...

Under a coloured noise (``--noise``, a shape of ``noise_coverage.py``) the
datasets are drawn with that noise and the yardstick is the likelihood-ratio
test that knows the true noise model, by its asymptotic power: the GLS
noncentrality lambda(s) of the effect's noise-free signal against the
baseline's Jacobian under the noise's exact covariance
(``rotcal.simulate.noise_covariance``), computed for every seed at the grid's middle
size and at twice it (the exponent of lambda in the size, 2 for a linear
effect), and the power P(noncentral chi-square(k, lambda) > its threshold)
averaged over the seeds. Clipping is left out there (its GLR is not a
smooth extension and assumes white noise).

Prints the Markdown table (docs/power.md, docs/measured.md) and the run's
cost (each dataset's CPU time, summed: over two cores, the wall time on a
quiet two-core machine), and writes the plot (``--plot``, default
docs/power_curves.png).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.optimize import brentq, minimize
from scipy.stats import chi2, ncx2, norm
from threadpoolctl import threadpool_limits

from rotcal.config import DiagnosisConfig, RunConfig, RunSection
from rotcal.diagnose import Diagnosis, _start
from rotcal.diagnose.clipping import quantum
from rotcal.diagnose.fitting import score
from rotcal.diagnose.glr import clipping_glr, clipping_threshold, glr, null_fit
from rotcal.diagnose.model import predict
from rotcal.ingest.dataset import load_dataset
from rotcal.model.effects import effect_named, names
from rotcal.model.physics import AXES, CHANNELS
from rotcal.model.results import IntrinsicResult
from rotcal.run.recommended import diagnose_stage
from rotcal.run.stages import Reductions, determined, reduce, segment_and_fit
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.core import dut_noise
from rotcal.simulate.noise_covariance import SampleCovariance, noncentrality

sys.path.insert(0, str(Path(__file__).resolve().parent))
from noise_coverage import SHAPES, noise_request  # noqa: E402 (the script beside this one)

SPAN = (2.5, 4.0)   # the grid from this factor below to this factor above the GLR's estimated 50 % size
CLIP_SIGMAS = (1.0, 4.0)   # clipping: limits from 1 to 4 noise standard deviations above the largest output
CLIP_MEASURE = "expected samples beyond the limit"
# Option keys that give an effect's shape, not its size: kept as drawn when the size is scaled.
SHAPE = frozenset({"axis", "ripple_phase_deg", "warmup_k", "tau_frac", "start_c", "step_k", "step_frac"})
ALPHA = DiagnosisConfig().false_alarm
NOISE_SPAN = (1.5, 16.0)   # under coloured noise: from this factor below to this factor above the oracle's 50 % size
NOISE_SEED = 0            # the noise shape's draw (``noise_request``; the mix has none)
CLIP_CALIBRATIONS = 3   # clean datasets whose null model calibrates the clipping GLR by Monte Carlo


def request(name: str, size: float, rng: np.random.Generator) -> str:
    """The effect ``name`` drawn as the acceptance scenarios draw it
    (``scenarios.draw_effect``: sign, axis, channel and shape), its size
    measure (``size_of``) then scaled to ``size`` with every other magnitude
    in proportion (thermal's tcs with its tco; channel_delay's delays, the
    largest being the size)."""
    effect = effect_named(name)
    low, high = effect.sizes
    drawn = effect.draw(rng.uniform(low, high), rng.choice([-1.0, 1.0]), rng.choice(AXES),
                        rng.choice(("u", "v", "w")), rng)
    head, body = drawn.split(":", 1)
    params = dict(kv.split("=") for kv in body.split(","))
    measure = [k for k in params if k not in SHAPE and not k.startswith("tcs_")]
    factor = size / max(abs(float(params[k])) for k in measure)
    scaled = {k: v if k in SHAPE else f"{float(v) * factor:.6g}" for k, v in params.items()}
    return head + ":" + ",".join(f"{k}={v}" for k, v in scaled.items())


def true_candidates(layout, name: str, req: str) -> tuple:
    """The diagnosis's extensions of the simulated effect where it acts: its
    axis, or each channel it was given on (every channel for a dataset-wide one)."""
    params = dict(kv.split("=") for kv in req.split(":", 1)[1].split(","))
    axis = params.get("axis")
    on = {c for c in CHANNELS if any(k.endswith(f"_{c}") or k.endswith(f"_{c}_s") for k in params)}
    return tuple(c for c in layout.candidates if c.effect == name
                 and (c.scope == "" or c.scope == axis or c.scope in on))


@dataclass(frozen=True)
class Job:
    effect: str       # the simulated effect, "" for a clean dataset
    size: float
    req: str          # the simulator request ("" for none)
    seed: int
    workdir: str
    noise: str = ""      # the simulator's noise request ("" the DUT's white noise)
    oracle: bool = False  # compute the oracle's noncentrality (coloured noise) at this size and twice it


def diagnosed(path: Path) -> tuple[tuple[IntrinsicResult, ...], Diagnosis]:
    """The baseline results and the diagnosis of a dataset: ``run_dataset``'s
    stages up to the diagnosis, with the default configuration (the stages
    after it, metrology and the written outputs, do not change it)."""
    config = RunConfig(run=RunSection(workers=1))
    with threadpool_limits(limits=1, user_api="blas"):
        ds = load_dataset(path, None, config.limits, 1)
        seg = segment_and_fit(ds, config)
        reductions = reduce(seg, ds)
        results, _, _ = determined(reductions, seg, path)
        assert isinstance(reductions, Reductions)
        diagnosis, _ = diagnose_stage(seg, reductions, results, ds, config)
    assert diagnosis is not None
    return results, diagnosis


def run_job(job: Job) -> dict:
    """Simulate one dataset, run rotcal on it, and compute the GLR statistic
    of its true extension (and, clean, each candidate's score p-value)."""
    began = cpu_seconds()
    req = clip_request(job) if job.effect == "clipping" else job.req
    spec = (SimulationSpec().with_noise(job.noise) if job.noise else SimulationSpec()).with_effects(*([req] if req else []))
    data = Path(job.workdir) / f"{job.effect or 'clean'}_{job.seed}_{job.size:.6g}"
    write_dataset(simulate(spec, job.seed), spec, data / "data")
    results, diagnosis = diagnosed(data / "data")
    found = diagnosis.findings.filter(diagnosis.findings["detected"])["effect"].to_list()
    out = {"effect": job.effect, "size": job.size, "req": req, "seed": job.seed,
           "named": job.effect in found, "findings": found}
    with threadpool_limits(limits=1, user_api="blas"):
        final = diagnosis.final
        null = null_fit(final.obs, final.layout, _start(final.layout, sorted(
            results, key=lambda r: (abs(r.rate_hz), r.rate_hz))))
        if job.noise:
            out["noise"] = job.noise
            if job.effect:
                out["k"] = sum(len(c.names) for c in true_candidates(final.layout, job.effect, req))
            if job.oracle:
                out["lambda"] = oracle_lambdas(job, null)
            if not job.effect:
                out["clean_p"] = {c.key: score(null, (c,)).p_value for c in final.layout.candidates}
            out["cpu_s"] = cpu_seconds() - began
            return out
        if job.effect == "clipping" or not job.effect:
            out["clip_glr"] = clipping_glr(null, quantum(final.obs.y))
        if job.effect == "clipping":   # its size: the expected number of samples beyond the limit
            limit = float(req.split("=")[1])
            out["size"] = float(norm.sf((limit - null.ev.pred) / null.sigma[None, :]).sum())
        if job.effect and job.effect != "clipping":
            out["glr"], out["k"] = glr(null, true_candidates(final.layout, job.effect, req))
        if not job.effect:   # calibration: every candidate's score p-value and GLR on clean data
            out["clean_p"] = {c.key: score(null, (c,)).p_value for c in final.layout.candidates}
            out["clean_glr"] = {c.key: glr(null, (c,))[0] for c in final.layout.candidates}
            out["k_of"] = {c.key: len(c.names) for c in final.layout.candidates}
            if job.seed < 1000 + CLIP_CALIBRATIONS:
                out["clip_threshold"] = clipping_threshold(null, quantum(final.obs.y), ALPHA, 200_000,
                                                           np.random.default_rng(job.seed))
    out["cpu_s"] = cpu_seconds() - began
    return out


def rescaled(req: str, factor: float) -> str:
    """An effect request with its size scaled by ``factor``: every magnitude
    (not its shape keys) in proportion, as ``request`` scales them."""
    head, body = req.split(":", 1)
    params = dict(kv.split("=") for kv in body.split(","))
    return head + ":" + ",".join(f"{k}={v if k in SHAPE else f'{float(v) * factor:.6g}'}" for k, v in params.items())


def oracle_lambdas(job: Job, null) -> list[float]:
    """The noncentrality lambda of the likelihood-ratio test that knows the
    true noise, at the job's size and at twice it: the GLS distance
    (``simulate.noise_covariance.noncentrality``, exact conjugate-gradient solves on
    the samples the diagnosis fits, the logger's pauses as gaps in the
    sensor's grid) of delta, the noise-free output with the effect less the
    noise-free output without it (the same seed: DUT, plan and effect
    shape), from the span of the baseline's Jacobian J (offsets and
    responsivities per rate, by central differences of the diagnosis's
    model at the null fit; the baseline is linear, so exact), summed over
    the three channels (independent, the same noise model each)."""
    base = SimulationSpec()
    quiet = replace(base, dut=replace(base.dut, noise_std=0.0, integer_output=False))
    noise = dut_noise(base.with_noise(job.noise))
    assert noise is not None
    fs_hz = 1 / base.plan.dt_s
    clean = simulate(quiet, job.seed).samples
    t_ns = clean["t_ns"].to_numpy()
    grid = np.round((t_ns - t_ns[0]) / 1e9 * fs_hz).astype(np.int64)
    obs = null.obs
    rows = np.searchsorted(t_ns, np.round(obs.motion.t_s * 1e9).astype(np.int64))
    assert np.array_equal(t_ns[np.minimum(rows, t_ns.size - 1)], np.round(obs.motion.t_s * 1e9).astype(np.int64))
    signals = []
    for factor in (1.0, 2.0):
        with_effect = simulate(quiet.with_effects(rescaled(job.req, factor)), job.seed).samples
        signals += [(with_effect[c].to_numpy() - clean[c].to_numpy())[rows] for c in CHANNELS]
    layout = null.layout

    def column(name: str) -> np.ndarray:
        i, h = layout.index[name], 1.0
        up, down = null.beta.copy(), null.beta.copy()
        up[i] += h
        down[i] -= h
        return (predict(obs, up, layout, (), null.clip, null.structure)
                - predict(obs, down, layout, (), null.clip, null.structure)) / (2 * h)
    names_of = [[n for n in layout.names[:layout.n_base] if n.split(".")[2] == str(r)] for r in range(3)]
    basis = np.column_stack([column(n)[:, 0] for n in names_of[0]])
    # the baseline's regressors (1 and a / g per rate) are the same on every channel: checked on one column each
    for r in (1, 2):
        assert np.allclose(column(names_of[r][-1])[:, r], basis[:, -1], rtol=1e-9, atol=1e-9)
    cov = SampleCovariance(noise, fs_hz, grid[rows], int(grid[-1]) + 1)
    lam = noncentrality(cov, np.column_stack(signals), basis, rtol=1e-8)
    return [float(lam[:3].sum()), float(lam[3:].sum())]


def oracle_power(rows: list[dict], size: float) -> float:
    """The oracle's power at ``size``: over the datasets with a noncentrality,
    the mean of P(noncentral chi-square(k, lambda) > chi-square(k)'s upper
    ``ALPHA`` quantile), each lambda carried from the dataset's size as
    size^p, p its exponent between the size and twice it."""
    out = []
    for r in rows:
        lam, lam2 = r["lambda"]
        p = float(np.log2(lam2 / lam)) if lam > 0 and lam2 > 0 else 2.0
        out.append(ncx2.sf(chi2.isf(ALPHA, r["k"]), r["k"], min(lam * (size / r["size"]) ** p, 1e9)))
    return float(np.mean(out))


def oracle_size(rows: list[dict], power: float) -> float:
    """The size at which the oracle's power is ``power`` (bisection in log size)."""
    centre = float(np.exp(np.mean(np.log([r["size"] for r in rows]))))
    return float(np.exp(brentq(lambda x: oracle_power(rows, float(np.exp(x))) - power,
                               np.log(centre) - 12, np.log(centre) + 12, xtol=1e-10)))


def cpu_seconds() -> float:
    """CPU time of this process and its finished children (user and system):
    what a dataset costs, whatever else shares the cores."""
    own, children = (resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def clip_request(job: Job) -> str:
    """A limit ``job.size`` noise standard deviations above the largest
    noise-free output (the simulator's ``below_max=0`` puts it at that
    output, rounded down): clipping fades as the limit rises above the noise."""
    spec = SimulationSpec().with_effects("clipping:below_max=0")
    peak = simulate(spec, job.seed).truth["effects"][0]["parameters"]["clip_high"] + 0.5
    return f"clipping:clip_high={np.floor(peak + job.size * SimulationSpec().dut.noise_std):.0f}"


def pilot_jobs(sizes: dict[str, float], stage: int, workdir: str, noise: str = "") -> list[Job]:
    """One dataset per effect of ``sizes`` at its size."""
    return [Job(name, sizes[name], request(name, sizes[name], np.random.default_rng([k, 0])), 10000 + 100 * stage + k,
                workdir, noise, bool(noise)) for k, name in enumerate(names()) if name in sizes]


def centres(pool: ProcessPoolExecutor, effects: set[str], workdir: str, noise: str = "") -> dict[str, float]:
    """Each effect's ``centre`` from a pilot at the low end of its catalogue
    range, refined by a second pilot there (far above the limit, the
    statistic of a misfit grows faster than the size squared). Under a
    coloured noise, the oracle's 50 % size from one pilot's noncentrality
    (exact, so one stage)."""
    sizes = {name: effect_named(name).sizes[0] for name in names() if name in effects - {"clipping"}}
    if noise:
        pilots = list(pool.map(run_job, pilot_jobs(sizes, 0, workdir, noise)))
        for r in pilots:
            print(f"pilot {r['effect']}: size {r['size']:.4g}, k {r['k']}, lambda {r['lambda'][0]:.4g} "
                  f"(twice the size {r['lambda'][1]:.4g}), {r['cpu_s']:.1f} CPU s", flush=True)
        return {r["effect"]: oracle_size([r], 0.5) for r in pilots}
    for stage in range(2):
        sizes = {r["effect"]: centre(r) for r in pool.map(run_job, pilot_jobs(sizes, stage, workdir))}
    return sizes


def centre(pilot: dict) -> float:
    """The size where the GLR test has about 50 % power, from one pilot
    dataset: its statistic's noncentrality (Lambda - k) grows as the size
    squared, and 50 % power needs a noncentrality of about the threshold
    less k - 1 (the median of a noncentral chi-square lies near its mean)."""
    k = pilot["k"]
    need = chi2.isf(ALPHA, k) - k + 1
    return pilot["size"] * float(np.sqrt(need / max(pilot["glr"] - k, 1.0)))


def jobs(effects: set[str], centres: dict[str, float], n_seeds: int, n_points: int, n_clean: int,
         workdir: str, noise: str = "") -> list[Job]:
    """The grid of every effect, ``n_points`` sizes from ``SPAN[0]`` below to
    ``SPAN[1]`` above its pilot centre (clipping: limits ``CLIP_SIGMAS``
    above its largest output), shapes drawn per seed (the same across sizes);
    and the clean datasets, the last third of them with a logged warm-up
    (thermal with zero coefficients) so that the thermal test is calibrated too.
    Under a coloured noise (``noise``) the grid spans ``NOISE_SPAN`` about the
    oracle's 50 % size, and the datasets of its middle size compute the oracle."""
    out = [Job("", 0.0, "", 1000 + s, workdir, noise) for s in range(n_clean - n_clean // 3)]
    out += [Job("", 0.0, "thermal:tco_u=0,tcs_u=0", 1500 + s, workdir, noise) for s in range(n_clean // 3)]
    span = NOISE_SPAN if noise else SPAN
    for k, name in enumerate(names()):
        if name not in effects:
            continue
        grid = (np.linspace(*CLIP_SIGMAS, n_points) if name == "clipping"
                else centres[name] * np.geomspace(1 / span[0], span[1], n_points))
        for i, size in enumerate(grid):
            for s in range(n_seeds):
                req = "" if name == "clipping" else request(name, float(size), np.random.default_rng([k, s]))
                out.append(Job(name, float(size), req, 20000 + 1000 * k + 100 * i + s, workdir, noise,
                               bool(noise) and i == n_points // 2))
    return out


def probit(sizes: np.ndarray, hits: np.ndarray) -> tuple[float, float]:
    """(ln s50, w) of P(s) = Phi((ln s - ln s50) / w) by maximum likelihood
    over the binomial outcomes ``hits`` (0/1 per dataset)."""
    x = np.log(sizes)

    def nll(p: np.ndarray) -> float:
        prob = np.clip(norm.cdf((x - p[0]) / np.exp(p[1])), 1e-12, 1 - 1e-12)
        return -float(np.sum(hits * np.log(prob) + (1 - hits) * np.log1p(-prob)))
    start = np.array([np.median(x), np.log(0.5)])
    best = minimize(nll, start, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 4000})
    return float(best.x[0]), float(np.exp(best.x[1]))


def clip_threshold(clean: list[dict]) -> float:
    """The clipping GLR's threshold at rotcal's false-alarm rate ``ALPHA``:
    the Monte Carlo quantile of its null distribution (``glr.clipping_threshold``),
    the median over the calibrating datasets. Every other effect's GLR
    threshold is chi-square(k)'s upper ``ALPHA`` quantile, k its parameters
    (its calibration on clean data is reported by ``calibration``)."""
    return float(np.median([r["clip_threshold"] for r in clean if "clip_threshold" in r]))


def calibration(clean: list[dict], clip_threshold: float) -> list[str]:
    """Clean datasets against the nominal rates: datasets with any finding;
    the diagnosis's per-test score p-values and the GLR statistics of every
    candidate (probability-integral transform against chi-square(k))."""
    p = np.array([v for r in clean for v in r["clean_p"].values()])
    u = np.array([chi2.sf(r["clean_glr"][key], r["k_of"][key]) for r in clean for key in r["clean_glr"]])
    clip = np.array([r["clip_glr"] for r in clean])
    any_finding = sum(bool(r["findings"]) for r in clean)
    warm = sum(any(k.startswith("thermal") for k in r["clean_glr"]) for r in clean)
    lines = [f"- clean datasets: {len(clean)}, {any_finding} with any finding ({warm} of them with a logged "
             "warm-up, where thermal is tested too)"]
    for name, values in (("diagnosis score test", p), ("GLR of each candidate", u)):
        rates = ", ".join(f"{np.mean(values < a):.3f} at {a:g}" for a in (0.1, 0.01, 0.001))
        lines.append(f"- {name}: {values.size} per-test p-values on clean data, fraction below level: {rates}; "
                     f"none below {ALPHA:g}: {int(np.sum(values < ALPHA))} of {values.size}")
    lines.append(f"- clipping GLR: Monte Carlo threshold {clip_threshold:.2f} at {ALPHA:g}; clean statistics "
                 f"median {np.median(clip):.2f}, largest {clip.max():.2f}, {int(np.sum(clip > clip_threshold))} "
                 f"of {clip.size} above it")
    return lines


def detections(results: list[dict]) -> Iterator[tuple[str, list[dict], np.ndarray, np.ndarray]]:
    """Per effect with outcomes, in the catalogue's order: its outcomes,
    their sizes and rotcal's detections (0/1)."""
    for name in names():
        rs = [r for r in results if r["effect"] == name]
        if rs:
            yield name, rs, np.array([r["size"] for r in rs]), np.array([r["named"] for r in rs], float)


def curves(results: list[dict], clip_threshold: float) -> dict[str, dict]:
    """Per effect: sizes, rotcal's and the GLR's detections (0/1), the
    probit fits and the 50 % and 80 % power sizes."""
    z80 = norm.ppf(0.8)
    out = {}
    for name, rs, sizes, rot in detections(results):
        if name == "clipping":
            best = np.array([r["clip_glr"] > clip_threshold for r in rs], float)
        else:
            best = np.array([r["glr"] > chi2.isf(ALPHA, r["k"]) for r in rs], float)
        fits = {kind: probit(sizes, hits) for kind, hits in (("rotcal", rot), ("glr", best))}
        out[name] = {"sizes": sizes, "rotcal": rot, "glr": best, "fits": fits,
                     "k": rs[0].get("k", 1),
                     "s50": {kind: float(np.exp(m)) for kind, (m, w) in fits.items()},
                     "s80": {kind: float(np.exp(m + z80 * w)) for kind, (m, w) in fits.items()}}
    return out


def noise_curves(results: list[dict]) -> dict[str, dict]:
    """Under a coloured noise, per effect: sizes, rotcal's detections and
    probit, and the oracle's 50 % and 80 % sizes (``oracle_size``) with the
    exponents of its noncentrality in the size (2: quadratic)."""
    z80 = norm.ppf(0.8)
    out = {}
    for name, rs, sizes, rot in detections(results):
        m, w = probit(sizes, rot)
        oracle = [r for r in rs if "lambda" in r]
        out[name] = {"sizes": sizes, "rotcal": rot, "fits": {"rotcal": (m, w)}, "k": rs[0]["k"], "oracle": oracle,
                     "exponents": [float(np.log2(r["lambda"][1] / r["lambda"][0])) for r in oracle],
                     "s50": {"rotcal": float(np.exp(m)), "glr": oracle_size(oracle, 0.5)},
                     "s80": {"rotcal": float(np.exp(m + z80 * w)), "glr": oracle_size(oracle, 0.8)}}
    return out


def noise_table(curve: dict[str, dict]) -> str:
    lines = ["| effect | size measure | k | rotcal s50 | oracle s50 | ratio s50 | rotcal s80 | oracle s80 | ratio s80 "
             "| lambda exponent |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, c in curve.items():
        s50, s80, p = c["s50"], c["s80"], c["exponents"]
        lines.append(f"| {name} | {effect_named(name).size_of.split(' (')[0]} | {c['k']} | {s50['rotcal']:.3g} | "
                     f"{s50['glr']:.3g} | {s50['rotcal'] / s50['glr']:.2f} | {s80['rotcal']:.3g} | {s80['glr']:.3g} | "
                     f"{s80['rotcal'] / s80['glr']:.2f} | {min(p):.3f} to {max(p):.3f} |")
    return "\n".join(lines)


def noise_calibration(clean: list[dict]) -> list[str]:
    """Clean datasets under the noise: those with any finding (rotcal's
    false alarms), and the white-noise score test's p-values at the plain
    baseline (how far from calibrated a test blind to the noise would be)."""
    p = np.array([v for r in clean for v in r["clean_p"].values()])
    rates = ", ".join(f"{np.mean(p < a):.3f} at {a:g}" for a in (0.1, 0.01, 0.001))
    return [f"- clean datasets: {len(clean)}, {sum(bool(r['findings']) for r in clean)} with any finding "
            f"({', '.join(sorted({f for r in clean for f in r['findings']})) or 'none'})",
            f"- the white-noise score test at the plain baseline (each candidate against the null fit, the "
            f"diagnosis's own tests add the noise model and the offsets' wander): {p.size} per-test p-values on "
            f"clean data, fraction below level: {rates}; below {ALPHA:g}: {int(np.sum(p < ALPHA))} of {p.size}"]


def table(curve: dict[str, dict]) -> str:
    lines = ["| effect | size measure | catalogue range | k | rotcal s50 | GLR s50 | ratio s50 | rotcal s80 | GLR s80 | ratio s80 |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, c in curve.items():
        e = effect_named(name)
        s50, s80 = c["s50"], c["s80"]
        measure, catalogued = ((CLIP_MEASURE, "-") if name == "clipping"
                               else (e.size_of.split(" (")[0], f"{e.sizes[0]:g} to {e.sizes[1]:g}"))
        lines.append(f"| {name} | {measure} | {catalogued} | "
                     f"{c['k'] if name != 'clipping' else '-'} | {s50['rotcal']:.3g} | {s50['glr']:.3g} | "
                     f"{s50['rotcal'] / s50['glr']:.2f} | {s80['rotcal']:.3g} | {s80['glr']:.3g} | "
                     f"{s80['rotcal'] / s80['glr']:.2f} |")
    return "\n".join(lines)


def plot(curve: dict[str, dict], path: Path) -> None:
    """One panel per effect: observed detection fractions per size and the
    fitted probits, rotcal against the GLR, the catalogue range shaded."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 5, figsize=(17, 6.5), sharey=True)
    for ax, (name, c) in zip(axes.flat, curve.items()):
        grid = np.unique(c["sizes"])
        fine = np.geomspace(grid[0], grid[-1], 200)
        if name != "clipping":
            ax.axvspan(*effect_named(name).sizes, color="0.92")
        if "oracle" in c:
            ax.plot(fine, [oracle_power(c["oracle"], float(s)) for s in fine], "-", color="C3",
                    label="LR test, true noise")
        for kind, colour, label in (("rotcal", "C0", "rotcal diagnosis"), ("glr", "C3", "GLR, true model")):
            if kind not in c["fits"]:
                continue
            m, w = c["fits"][kind]
            frac = [c[kind][c["sizes"] == s].mean() for s in grid]
            ax.plot(grid, frac, "o", color=colour, ms=4)
            ax.plot(fine, norm.cdf((np.log(fine) - m) / w), "-", color=colour, label=label)
        ax.set_xscale("log")
        ax.axhline(0.5, color="0.6", lw=0.6)
        ax.set_title(f"{name}: ratio {c['s50']['rotcal'] / c['s50']['glr']:.2f}", fontsize=9)
        ax.set_xlabel(CLIP_MEASURE if name == "clipping" else effect_named(name).size_of.split(" (")[0], fontsize=7)
        ax.tick_params(labelsize=7)
    for ax in axes.flat[len(curve):]:
        ax.axis("off")
    axes[0, 0].set_ylabel("detection probability")
    axes[1, 0].set_ylabel("detection probability")
    axes[0, 0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=90, format="png", metadata={"Software": None})
    plt.close(fig)


def loaded(paths: list[Path]) -> list[dict]:
    """Saved outcomes: each effect's from the last file holding it, the clean
    ones from the file holding most (a rerun of some effects keeps the
    larger calibration)."""
    files = [json.loads(p.read_text()) for p in paths]
    clean = max(([r for r in f if not r["effect"]] for f in files), key=len)
    chosen = {r["effect"]: f for f in files for r in f if r["effect"]}
    return clean + [r for name, f in chosen.items() for r in f if r["effect"] == name]


def runtime(results: list[dict], wall_s: float, cpu_s: float, workers: int) -> str:
    """The run's cost: the datasets' summed CPU time (``cpu_s`` of each, as
    saved), per kind, and that sum over two cores, the wall time on a quiet
    two-core machine; and this invocation's wall time and CPU time (with its
    workers), which on a shared machine say little."""
    timed = [r for r in results if "cpu_s" in r]
    total = sum(r["cpu_s"] for r in timed)
    kinds = {}
    for r in timed:
        kinds.setdefault(r["effect"] or "clean", []).append(r["cpu_s"])
    per = ", ".join(f"{k} {np.mean(v):.1f}" for k, v in kinds.items())
    return (f"- CPU time: {len(timed)} of {len(results)} datasets timed, {total:,.0f} CPU s in all "
            f"(per dataset, s: {per}); on 2 idle cores about {total / 2:,.0f} s wall ({total / 120:.0f} min)\n"
            f"- this invocation: {wall_s:,.0f} s wall, {cpu_s:,.0f} CPU s with its {workers} workers")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8, help="datasets per effect and size")
    parser.add_argument("--points", type=int, default=7, help="sizes per effect")
    parser.add_argument("--clean", type=int, default=24, help="clean calibration datasets")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="a smoke test: 1 seed, 2 sizes, 2 clean datasets")
    parser.add_argument("--plot", type=Path, default=Path("docs/power_curves.png"))
    parser.add_argument("--json", type=Path, help="also write every dataset's outcome here")
    parser.add_argument("--effects", nargs="+", choices=names(), help="only these effects (default: all; "
                        "under --noise all but clipping)")
    parser.add_argument("--noise", choices=SHAPES, default="white",
                        help="the noise shape (noise_coverage.py); not white: the oracle is the LR test that knows it")
    parser.add_argument("--load", type=Path, nargs="+",
                        help="tabulate saved outcomes (--json) instead of simulating: each effect's rows from the "
                             "last file holding it, the clean rows from the file holding most")
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.points, args.clean = 1, 2, 2
    noise = noise_request(args.noise, NOISE_SEED)
    if args.effects is None:
        args.effects = [n for n in names() if not (noise and n == "clipping")]
    began, cpu_began = time.perf_counter(), cpu_seconds()
    if args.load:
        results = loaded(args.load)
    else:
        with tempfile.TemporaryDirectory() as workdir, ProcessPoolExecutor(args.workers) as pool:
            effects = set(args.effects)
            results = list(pool.map(run_job, jobs(effects, centres(pool, effects, workdir, noise), args.seeds,
                                                  args.points, args.clean, workdir, noise)))
    noise = next((r["noise"] for r in results if r.get("noise")), "")
    if noise:
        coloured(results, args, noise, began, cpu_began)
        return
    clean = [r for r in results if not r["effect"]]
    threshold = clip_threshold(clean)
    curve = curves([r for r in results if r["effect"]], threshold)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    plot(curve, args.plot)
    print(table(curve))
    print()
    print(f"Per-test false-alarm rate {ALPHA:g} for both tests; {args.seeds} datasets per size, {args.points} sizes "
          f"per effect from {SPAN[0]:g}x below to {SPAN[1]:g}x above the GLR's pilot 50 % size "
          f"(clipping: limits {CLIP_SIGMAS[0]:g} to {CLIP_SIGMAS[1]:g} noise sd above the largest output).")
    print("\n".join(calibration(clean, threshold)))
    print(runtime(results, time.perf_counter() - began, cpu_seconds() - cpu_began, args.workers))


def coloured(results: list[dict], args: argparse.Namespace, noise: str, began: float, cpu_began: float) -> None:
    """Tabulate a run under a coloured noise: rotcal against the oracle."""
    if args.json and not args.load:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    clean = [r for r in results if not r["effect"]]
    curve = noise_curves([r for r in results if r["effect"]])
    plot(curve, args.plot)
    print(noise_table(curve))
    print()
    effect_rows = [r for r in results if r["effect"]]
    points = max(len({r["size"] for r in effect_rows if r["effect"] == e}) for e in curve)
    seeds = max(sum(r["effect"] == e and r["size"] == s for r in effect_rows) for e in curve for s in curve[e]["sizes"])
    print(f"Noise {noise}. Per-test false-alarm rate {ALPHA:g}; {seeds} datasets per size, {points} sizes "
          f"per effect from {NOISE_SPAN[0]:g}x below to {NOISE_SPAN[1]:g}x above the oracle's pilot 50 % size; the "
          f"oracle from the noncentralities of the {sum('lambda' in r for r in results)} datasets at the middle size.")
    print("\n".join(noise_calibration(clean)))
    print(runtime(results, time.perf_counter() - began, cpu_seconds() - cpu_began, args.workers))


if __name__ == "__main__":
    main()
