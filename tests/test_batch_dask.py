"""The same jobs on a Dask cluster (a LocalCluster reached through its
address, from a configuration file) give the local process pool's outputs:
results do not depend on the executor. (The crash test compares the pool
with a single in-process worker.)"""

from dataclasses import replace

from distributed import LocalCluster

from rotcal.batch.runner import run_batch
from rotcal.config import BatchConfig, load_config

from batch_support import NO_DIAGNOSIS, SERIAL, assert_same_tables, make_root, manifest_rows, result_tables

TIMING = {"run_id", "started_at", "finished_at", "duration_s"}


def test_dask_cluster_gives_the_process_pool_outputs(tmp_path):
    root = tmp_path / "root"
    make_root(root, range(1, 5))
    (root / "bad.csv").write_text("t,u,v,w\n0,1,2\n")
    pool = run_batch(root, tmp_path / "pool", replace(SERIAL, batch=BatchConfig(workers=2)))
    # Worker threads in this process, reached over TCP like a remote cluster
    # (jobs and results are serialised): worker processes would only add start-up time.
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp", dashboard_address=None) as cluster:
        config = tmp_path / "dask.toml"
        config.write_text(NO_DIAGNOSIS + f'[batch]\nexecutor = "dask://{cluster.scheduler_address.removeprefix("tcp://")}"\n')
        dask = run_batch(root, tmp_path / "dask", load_config(config))
    assert (pool.workers, dask.workers) == (2, 2)
    for summary in (pool, dask):
        assert (summary.ok, summary.quarantined, summary.errors) == (4, 1, 0)
    assert_same_tables(result_tables(tmp_path / "pool"), result_tables(tmp_path / "dask"))

    def rows(out):
        return {k: {c: v for c, v in r.items() if c not in TIMING} for k, r in manifest_rows(out).items()}

    assert rows(tmp_path / "dask") == rows(tmp_path / "pool")
