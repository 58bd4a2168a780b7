"""A simulated 2-node Ray cluster (``ray.cluster_utils.Cluster``): seeds spread over both nodes, and
the run survives removing the node one of them trains on (its actor restarts on the other node and
resumes from its checkpoint; checkpoints live on storage both "nodes" see, as on a real cluster's
shared filesystem).

It needs its own Ray, so it shuts the session's down first (the next test that asks for
``ray_session`` starts it again).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cluster.runtime import ray_backend
from cluster.runtime.rundir import RunDir
from population.config import load_config

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")


@pytest.fixture
def two_nodes():
    import os

    import ray
    from ray.cluster_utils import Cluster

    from cluster.runtime.ray_backend import ray_process_launches

    # The auth mode conftest's ensure_ray sets for the session's Ray, without starting that Ray only to
    # shut it down (the compilation cache is in the environment the nodes inherit).
    os.environ["RAY_AUTH_MODE"] = "disabled"
    if ray.is_initialized():
        ray.shutdown()
    with ray_process_launches():
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        worker_node = cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address)
    try:
        yield cluster, worker_node
    finally:
        ray.shutdown()
        cluster.shutdown()


def test_seeds_spread_over_two_nodes_and_the_run_survives_losing_one(tmp_path, two_nodes):
    cluster, worker_node = two_nodes
    config = load_config(SMOKE, ["ppo.total_timesteps=1024", "run.checkpoint_every=2"])
    seen = {}

    def remove_worker_node(update, workers, _rows):
        if update == 2 and not seen:
            seen["nodes"] = workers.node_ids()
            cluster.remove_node(worker_node)

    summary = ray_backend.train_population(
        config, tmp_path / "run", show_progress=False, evaluate=False, on_chunk=remove_worker_node
    )
    assert len(set(seen["nodes"])) == 2  # one seed per node (SPREAD)
    assert summary["restarts"] >= 1
    manifest = RunDir(tmp_path / "run").read_manifest()
    assert manifest["status"] == "finished" and manifest["update"] == 8
    events = manifest["restart_events"]
    assert all(event["restored_update"] >= 2 for event in events)  # at most one checkpoint interval lost
    rows = RunDir(tmp_path / "run").read_metrics()
    assert sorted((int(r["seed"]), int(r["update"])) for r in rows) == [(s, u) for s in (0, 1) for u in range(1, 9)]
