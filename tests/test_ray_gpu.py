"""The Ray backend on a GPU node, simulated on the CPU: what ``cluster.num_gpus`` (default ``auto``) gives each
actor, the environment it gets (no ``JAX_PLATFORMS=cpu``, XLA's deterministic GPU ops), and what the run's
header and environment.json say about where each actor trains.

The run test needs a Ray that declares GPUs this machine does not have (``ray.init(num_gpus=2)``, through
``start_local``, the function the session's Ray starts with), so it shuts the session's Ray down first; the
next test that asks for ``ray_session`` starts it again. Ray hands the actors GPU ids and
``CUDA_VISIBLE_DEVICES`` as on a GPU node; their JAX, a CPU build, trains on the CPU and says so.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
from pathlib import Path

import pytest

from cluster.cli import main
from cluster.runtime import ray_backend
from cluster.runtime.rundir import RunDirError
from population import numerics
from population.config import ClusterConfig, load_config

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")
FLAG = numerics.DETERMINISTIC_FLAG


@pytest.mark.parametrize(
    "nodes, actors, expected",
    [
        ([1], 2, 0.5),  # one GPU shared by two actors
        ([4], 2, 1.0),  # never more than one GPU an actor unless asked for
        ([2], 3, 0.5),  # 2 GPUs x 2 halves place 3 actors
        ([1, 1], 3, 0.5),  # two nodes of one GPU: a half fits on each
        ([8, 0], 10, 0.5),
        ([0, 0], 2, 0.0),  # 0 only when Ray reports no GPU
        ([], 2, 0.0),
    ],
)
def test_auto_shares_the_gpus_ray_reports_among_the_actors(monkeypatch, nodes, actors, expected):
    monkeypatch.setattr(ray_backend, "_node_resources", lambda: [{"CPU": 4.0, "GPU": float(g)} for g in nodes])
    assert ray_backend.gpus_per_actor(ClusterConfig(), actors) == expected
    assert ray_backend.gpus_per_actor(ClusterConfig(num_gpus=2), actors) == 2.0  # a number is taken as it is
    assert ray_backend.gpus_per_actor(ClusterConfig(num_gpus=0), actors) == 0.0


def test_a_memory_fraction_above_an_actors_share_of_a_gpu_is_refused_naming_the_key(monkeypatch):
    """gpu-node.yaml's actors share one GPU (0.5 each); a gpu_memory_fraction of 0.9 made each preallocate 90 % of it,
    so the second actor could not start, and the run died with a misleading worker-death message."""
    monkeypatch.setattr(ray_backend, "_node_resources", lambda: [{"CPU": 4.0, "GPU": 1.0}])
    monkeypatch.setattr(ray_backend.ray, "cluster_resources", lambda: {"CPU": 4.0, "GPU": 1.0})
    config = load_config(SMOKE)  # 2 seeds, one actor each
    shared = lambda fraction: dataclasses.replace(  # noqa: E731
        config, cluster=dataclasses.replace(config.cluster, gpu_memory_fraction=fraction)
    )
    with pytest.raises(ray_backend.RayBackendError, match=r"cluster.gpu_memory_fraction: .*0.9 .*at most 0.5"):
        ray_backend.check_resources(shared(0.9), 2)
    ray_backend.check_resources(shared(0.5), 2)  # within its share
    ray_backend.check_resources(shared(0.9), 1)  # one actor has the whole GPU


def test_only_an_actor_without_a_gpu_is_pinned_to_the_cpu(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    cluster = ClusterConfig()
    without = ray_backend.actor_env(cluster, 0.0)
    assert without["JAX_PLATFORMS"] == "cpu" and "XLA_FLAGS" not in without
    assert ray_backend.actor_env(cluster) == without  # auto left unresolved: an actor that asks for no GPU
    with_gpu = ray_backend.actor_env(cluster, 0.5)
    assert "JAX_PLATFORMS" not in with_gpu
    assert with_gpu["XLA_FLAGS"] == "${XLA_FLAGS} " + FLAG  # Ray expands ${XLA_FLAGS} on the node
    assert "XLA_FLAGS" not in ray_backend.actor_env(cluster, 0.5, deterministic=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_deterministic_ops=false")  # turned off explicitly: left so
    assert "XLA_FLAGS" not in ray_backend.actor_env(cluster, 1.0)
    assert "JAX_PLATFORMS" not in ray_backend.actor_env(ClusterConfig(num_gpus=1))


@pytest.fixture(scope="module")
def ray_with_gpus():
    import ray

    os.environ["RAY_AUTH_MODE"] = "disabled"  # as conftest's ensure_ray
    if ray.is_initialized():
        ray.shutdown()
    ray_backend.start_local(num_cpus=4, num_gpus=2)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_actors_get_the_gpus_ray_declares_and_say_where_they_train(tmp_path, capsys, ray_with_gpus):
    run = tmp_path / "run"
    assert main(["train", SMOKE, "--out", str(run), "--backend", "ray", "--no-eval"]) == 0
    err = capsys.readouterr().err
    record = json.loads((run / "environment.json").read_text())["drivers"][-1]
    assert record["run"] == {"precision": "float32", "deterministic": True}
    workers = record["workers"]
    assert [w["seeds"] for w in workers] == [[0], [1]]
    # auto: 2 GPUs, 2 actors -> one each, each its own (Ray's ids, and CUDA_VISIBLE_DEVICES set from them)
    assert [w["num_gpus"] for w in workers] == [1.0, 1.0]
    assert sorted(w["gpu_ids"][0] for w in workers) == ["0", "1"]
    assert all(w["cuda_visible_devices"] == w["gpu_ids"][0] for w in workers)
    # not pinned to the CPU: the actor sees what the driver's environment says, nothing forced
    assert all(w["jax_platforms"] == os.environ.get("JAX_PLATFORMS") for w in workers)
    # the deterministic flag appended to the node's own XLA_FLAGS (the session's test flags kept)
    session_flags = os.environ.get("XLA_FLAGS", "")
    assert all(w["xla_gpu_deterministic_ops"] and w["xla_flags"].startswith(session_flags) for w in workers)
    assert all(w["matmul_precision"] == "float32" for w in workers)
    # this jaxlib has no CUDA: the actors train on the CPU, and the run says so instead of hiding it
    assert all(w["device"] == "cpu" and w["worker"] == "Ray actor" for w in workers)
    assert "seeds 0-1 train on cpu (2 Ray actors, 1 GPU each)" in err
    assert "run.precision float32 (matmuls compute float32), run.deterministic true" in err
    assert err.count("GPU (ids ['") == 2 and "but JAX trains on the CPU there" in err


def test_explicit_gpus_beyond_the_declared_ones_fail_naming_the_key(tmp_path, capsys, ray_with_gpus):
    config = load_config(SMOKE, ["cluster.num_gpus=1.5"])  # 2 actors x 1.5 > 2 GPUs; no node has 1.5 either
    with pytest.raises(ray_backend.RayBackendError, match="cluster.num_gpus"):
        ray_backend.check_resources(config, 2)
    ray_backend.check_resources(load_config(SMOKE, ["cluster.num_gpus=0.5"]), 2)  # fits


def test_a_run_directory_a_network_file_system_shows_late_is_waited_for_then_refused(tmp_path, monkeypatch):
    """One look refused a run directory whose config.yaml an NFS client's negative-lookup cache still hid."""
    threading.Timer(0.7, (tmp_path / "config.yaml").write_text, ("{}\n",)).start()  # shows up after 0.7 s
    ray_backend.visible_run_dir(tmp_path)
    monkeypatch.setattr(ray_backend, "VISIBLE_TRIES", 2)
    with pytest.raises(RunDirError, match="not visible on the worker's node"):
        ray_backend.visible_run_dir(tmp_path / "absent")
