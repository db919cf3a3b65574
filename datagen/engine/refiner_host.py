"""One refiner per node (``RunSettings.shared_refiner``): a Ray actor per node holds the POCO network
and runs the network jobs of every task there (`datagen.pipeline.refine.poco.network_jobs.NetworkHost`).

Tasks stay the unit of retry and commit. Each task prepares its own jobs (queries, input draws) and
sends them to its node's host; the host answers each call with that call's probabilities, exactly
those of a refiner in the task's process (one job at a time), or, with ``refiner_batch`` > 1, the
encoder run on several jobs at once (for accelerators). A host that dies is restarted by Ray on the
same node (`HOST_RESTARTS`) and the calls it held are sent again (they are pure functions of their
jobs), so nothing is lost or duplicated; past its restarts, the tasks whose calls failed fail and
are retried like any task. A task on a node without a host (one that joined mid-job) refines in
its own process on the CPU.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

from datagen.errors import ConfigError
from schemas.config import GenerationConfig

if TYPE_CHECKING:  # torch comes with them: imported where a host or a hosted task runs
    from datagen.pipeline.refine.poco.network_jobs import NetworkJob, NetworkReply, RemoteNetwork

HOST_RESTARTS = 3
"""Times Ray restarts a node's host (and sends its pending calls again) before the calls fail."""
HOST_CALLS = 1024
"""Calls a host takes at once (Ray's ``max_concurrency``): every task on a node waits on it at most once."""


class RefinerHost:
    """The actor's body: the config's refiner network on ``device``, served by the `NetworkHost` its
    refiner kind's hosting builds (`schemas.refiners.RefinerKind.hosting`)."""

    def __init__(self, config_json: str, device: str, encoder_batch: int) -> None:
        import torch

        from datagen.pipeline.refine.factory import network_hosting

        torch.set_num_threads(1)  # the one CPU the actor reserves, as a worker's torch (`fixed_torch_threads`)
        config = GenerationConfig.model_validate_json(config_json)
        hosting = network_hosting(config)
        if hosting is None:
            raise ConfigError(f"refiner {config.refiner!r} has no network a shared host can run")
        self.host = hosting.host(config, device, encoder_batch)

    def run(self, jobs: list[NetworkJob]) -> NetworkReply:
        return self.host.run(jobs)

    def pid(self) -> int:
        return os.getpid()

    def served(self) -> int:
        return self.host.served


def host_name(prefix: str, node_id: str) -> str:
    return f"{prefix}-{node_id}"


def start_hosts(config: GenerationConfig, prefix: str, device: str, encoder_batch: int = 1) -> list[Any]:
    """A host on every alive node (with a GPU when ``device`` is 'cuda'), named `host_name`; returns
    their handles (the caller, the driver, owns them: they end with it or with `stop_hosts`)."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    actor = ray.remote(RefinerHost)
    handles = []
    for node in sorted(ray.nodes(), key=lambda node: str(node["NodeID"])):
        resources = node.get("Resources", {})
        if not node.get("Alive") or not resources.get("CPU"):
            continue
        if device == "cuda" and not resources.get("GPU"):
            continue
        options = {
            "name": host_name(prefix, node["NodeID"]),
            "get_if_exists": True,
            "num_cpus": 1,
            "num_gpus": 1 if device == "cuda" else 0,
            "max_restarts": HOST_RESTARTS,
            "max_task_retries": HOST_RESTARTS,
            "max_concurrency": HOST_CALLS,
            "scheduling_strategy": NodeAffinitySchedulingStrategy(node["NodeID"], soft=False),
        }
        handles.append(actor.options(**options).remote(config.model_dump_json(), device, encoder_batch))
    return handles


def stop_hosts(handles: Sequence[Any]) -> None:
    import ray

    for handle in handles:
        ray.kill(handle, no_restart=True)


def node_network(prefix: str) -> RemoteNetwork | None:
    """The host of the node this task runs on as the task's network, or None when the node has none."""
    import ray

    from datagen.pipeline.refine.poco.network_jobs import RemoteNetwork

    node_id = ray.get_runtime_context().get_node_id()
    try:
        handle = ray.get_actor(host_name(prefix, node_id))
    except ValueError:
        return None

    def call(jobs: list[NetworkJob]) -> NetworkReply:
        return cast("NetworkReply", ray.get(handle.run.remote(jobs)))

    return RemoteNetwork(call)
