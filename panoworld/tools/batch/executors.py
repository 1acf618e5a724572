"""Stage executors for dataset runs: a local subprocess with a thread budget, or one Ray task per stage.

The runner (panoworld.framework.pipeline.run) takes every cache decision; an executor only runs a stage it was handed.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from panoworld.core.errors import PipelineError
from panoworld.framework.dag import StageNode
from panoworld.framework.execute import run_with_params_file, runner_env, stage_command
from panoworld.framework.scene import Scene
from panoworld.framework.stage_params import params_to_dict
from panoworld.tools.precompute.run import thread_env


def needs_gpu(node: StageNode, params: Any) -> bool:
    """Whether the stage asks for a GPU with these params: `resources.gpu` > 0 and, when `resources.gpu_when` maps
    params to values ({backend: [wan-shortcut]}), one of those params has one of its values."""
    res = node.resources
    if not res.get("gpu"):
        return False
    when = res.get("gpu_when")
    if not when:
        return True
    values = params_to_dict(params)
    return any(str(values.get(k)) in {str(v) for v in vs} for k, vs in when.items())


def _run_with_params(template: list[str], params: dict, log: str, env_extra: dict[str, str]) -> tuple[int, float, float]:
    """Write the params file here (the machine that runs the stage, beside the log) and run the stage command."""
    return run_with_params_file(template, params, Path(log), False, env_extra)


class LocalStageExecutor:
    """Each stage as a local subprocess limited to `threads` threads (cores / concurrent scenes)."""

    kind = "local"

    def __init__(self, workers: int):
        self.workers = workers
        self.threads = max(1, (os.cpu_count() or 1) // max(workers, 1))

    def __call__(self, node: StageNode, scene: Scene, params: Any, echo: bool) -> tuple[int, float, float]:
        threads = min(self.threads, int(node.resources.get("cpu", 1)) or 1)
        template = stage_command(node, scene, "{params_file}", python="{python}")
        return _run_with_params(template, params_to_dict(params), str(scene.log_file(node.name)),
                                {**thread_env(threads), **runner_env(scene)})

    def close(self) -> None:
        pass


class RayStageExecutor:
    """Each stage as a Ray task with pipeline.yaml `resources`: num_cpus = cpu (capped at the cluster's CPUs / workers),
    num_gpus = gpu when the stage's params need a GPU (needs_gpu). Paths must be visible to every node (a shared
    file system) and the nodes must have this repository and its environment at the same paths."""

    kind = "ray"

    def __init__(self, workers: int, address: str | None = None):
        from panoworld.tools.precompute.run import RayExecutor

        self.ray = RayExecutor(workers, address).ray  # connects, or starts a local instance with `workers` CPUs
        res = self.ray.cluster_resources()
        self.cpus, self.gpus = float(res.get("CPU", 1)), float(res.get("GPU", 0))
        # Each of the `workers` scenes in flight may ask for at most its share of the cluster's CPUs (as the local
        # executor's cores / workers threads): a 2-CPU stage must not hold the whole of a small cluster.
        self.cpu_share = max(1.0, self.cpus / max(1, workers))
        self.remote = self.ray.remote(max_retries=0)(_run_with_params)

    def __call__(self, node: StageNode, scene: Scene, params: Any, echo: bool) -> tuple[int, float, float]:
        cpus = min(float(node.resources.get("cpu", 1)) or 1.0, self.cpu_share)
        gpus = float(node.resources.get("gpu", 1)) if needs_gpu(node, params) else 0.0
        if gpus > self.gpus:
            raise PipelineError(f"stage {node.name} needs {gpus:g} GPU(s) with these params but the Ray cluster has "
                                f"{self.gpus:g}; connect to a cluster with GPUs (--ray-address) or pick a CPU backend")
        template = stage_command(node, scene, "{params_file}", python="{python}")
        ref = self.remote.options(num_cpus=cpus, num_gpus=gpus).remote(
            template, params_to_dict(params), str(scene.log_file(node.name)), thread_env(int(cpus)))
        return tuple(self.ray.get(ref))

    def close(self) -> None:
        pass


def make_stage_executor(kind: str, workers: int, address: str | None = None):
    if kind == "local":
        if address:
            raise PipelineError("--ray-address needs --executor ray")
        return LocalStageExecutor(workers)
    if kind == "ray":
        try:
            return RayStageExecutor(workers, address)
        except RuntimeError as e:  # Ray missing
            raise PipelineError(str(e)) from None
    raise PipelineError(f"--executor {kind}: expected local or ray")
