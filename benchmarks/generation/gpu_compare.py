"""gpu_check's comparison and report: one task's refinements and labels on two devices, side by side.

Kept apart from the running (`benchmarks.generation.gpu_check`) so that the comparison can be tested
on made-up refinements, and so that a report can be rendered again from a saved JSON.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

REFERENCE = "cpu reference"
"""The label of the reference run: the CPU, as every dataset so far was refined."""


@dataclass(frozen=True)
class Refinement:
    """One refined observation: its view mask, the keys queried, p(inside) of each and R(O)."""

    mask: int
    queries: npt.NDArray[np.int64]
    prob: npt.NDArray[np.float32]
    kept: npt.NDArray[np.int64]


@dataclass
class TaskRun:
    """One task refined one way: the refinements in request order, the labels, and the wall seconds."""

    refinements: list[Refinement]
    labels: dict[int, tuple[int, str]]
    """case -> (label view mask, cover status) of every sample."""
    failures: dict[int, str]
    """case -> message of every case that could not be labelled."""
    cases: tuple[int, ...]
    task_seconds: float
    refine_seconds: float
    steps: dict[str, float] = field(default_factory=dict)
    """Wall seconds per step of `run_task`."""


@dataclass(frozen=True)
class RefinementDiff:
    """How one refined observation differs from the reference's."""

    mask: int
    kept_reference: int
    kept: int
    differing: int
    """Keys in exactly one of the two R(O)."""
    union: int
    max_prob_diff: float
    """Largest |p_ref - p| over the keys both queried (0 when none)."""
    same_queries: bool

    @property
    def share(self) -> float:
        """|R_ref xor R| / |R_ref or R| (0 when both are empty)."""
        return self.differing / self.union if self.union else 0.0


def compare_refinement(reference: Refinement, other: Refinement) -> RefinementDiff:
    if reference.mask != other.mask:
        raise ValueError(f"requests out of step: view mask {reference.mask:#x} against {other.mask:#x}")
    _, mine, theirs = np.intersect1d(reference.queries, other.queries, assume_unique=True, return_indices=True)
    deltas = np.abs(reference.prob[mine].astype(np.float64) - other.prob[theirs].astype(np.float64))
    return RefinementDiff(
        mask=reference.mask,
        kept_reference=int(reference.kept.size),
        kept=int(other.kept.size),
        differing=int(np.setxor1d(reference.kept, other.kept, assume_unique=True).size),
        union=int(np.union1d(reference.kept, other.kept).size),
        max_prob_diff=float(deltas.max()) if deltas.size else 0.0,
        same_queries=bool(np.array_equal(reference.queries, other.queries)),
    )


@dataclass(frozen=True)
class Comparison:
    """One variant's task against the reference's."""

    singles: int
    singles_identical: int
    cases: int
    """Multi-view cases refined."""
    cases_identical: int
    differing_keys: int
    union_keys: int
    share_max: float
    share_mean: float
    max_prob_diff: float
    same_queries: bool
    same_cases: bool
    samples: int
    labels_differing: int
    """Samples whose label or status differs, or that only one side has."""
    failures_equal: bool
    refinements: list[RefinementDiff]

    @property
    def refined_identical(self) -> bool:
        return self.singles_identical == self.singles and self.cases_identical == self.cases

    @property
    def labels_identical(self) -> bool:
        return self.same_cases and self.labels_differing == 0 and self.failures_equal

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["refinements"] = [dict(asdict(d), share=d.share) for d in self.refinements]
        out["refined_identical"] = self.refined_identical
        out["labels_identical"] = self.labels_identical
        return out


def compare_runs(reference: TaskRun, other: TaskRun) -> Comparison:
    """Every refinement and every label of ``other`` against ``reference`` (same task, same requests)."""
    if len(reference.refinements) != len(other.refinements):
        raise ValueError(f"{len(reference.refinements)} refinements against {len(other.refinements)}")
    diffs = [compare_refinement(a, b) for a, b in zip(reference.refinements, other.refinements, strict=True)]
    singles = [d for d in diffs if d.mask.bit_count() == 1]
    multi = [d for d in diffs if d.mask.bit_count() > 1]
    shares = [d.share for d in diffs]
    cases = sorted(set(reference.labels) | set(other.labels))
    return Comparison(
        singles=len(singles),
        singles_identical=sum(d.differing == 0 for d in singles),
        cases=len(multi),
        cases_identical=sum(d.differing == 0 for d in multi),
        differing_keys=sum(d.differing for d in diffs),
        union_keys=sum(d.union for d in diffs),
        share_max=max(shares, default=0.0),
        share_mean=float(np.mean(shares)) if shares else 0.0,
        max_prob_diff=max((d.max_prob_diff for d in diffs), default=0.0),
        same_queries=all(d.same_queries for d in diffs),
        same_cases=reference.cases == other.cases,
        samples=len(reference.labels),
        labels_differing=sum(reference.labels.get(c) != other.labels.get(c) for c in cases),
        failures_equal=reference.failures == other.failures,
        refinements=diffs,
    )


def run_json(run: TaskRun) -> dict[str, Any]:
    return {"task_seconds": run.task_seconds, "refine_seconds": run.refine_seconds, "steps": run.steps}


def summary(tasks: Sequence[dict[str, Any]], labels: Sequence[str]) -> dict[str, Any]:
    """Per variant over the tasks it ran: how many came out identical, the worst shares, the summed
    times (its own and the reference's on the same tasks), and how many runs raised."""
    out: dict[str, Any] = {}
    for label in labels:
        ran = [t for t in tasks if label in t["comparisons"]]
        compared = [t["comparisons"][label] for t in ran]
        out[label] = {
            "tasks": len(ran),
            "errors": sum(label in t["errors"] for t in tasks),
            "refined_identical_tasks": sum(c["refined_identical"] for c in compared),
            "labels_identical_tasks": sum(c["labels_identical"] for c in compared),
            "differing_keys": sum(c["differing_keys"] for c in compared),
            "union_keys": sum(c["union_keys"] for c in compared),
            "share_max": max((c["share_max"] for c in compared), default=0.0),
            "max_prob_diff": max((c["max_prob_diff"] for c in compared), default=0.0),
            "labels_differing": sum(c["labels_differing"] for c in compared),
            "samples": sum(c["samples"] for c in compared),
            "task_seconds": sum(t["runs"][label]["task_seconds"] for t in ran),
            "refine_seconds": sum(t["runs"][label]["refine_seconds"] for t in ran),
            "reference_task_seconds": sum(t["runs"][REFERENCE]["task_seconds"] for t in ran),
            "reference_refine_seconds": sum(t["runs"][REFERENCE]["refine_seconds"] for t in ran),
        }
    return out


def markdown(result: dict[str, Any]) -> str:
    """The report: the setting, one row per task and variant, one summary row per variant."""
    env, refiner = result["environment"], result["refiner"]
    labels = [v["label"] for v in result["variants"]]
    driver = f", driver {env['cuda_driver']}" if env.get("cuda_driver") else ""
    capability = f" (capability {env['device_capability']}{driver})" if env.get("device_capability") else ""
    warm = ", ".join(f"{k} {s:.2f} s" for k, s in result["warm_up_seconds"].items() if s is not None)
    out = [
        "# The poco refiner on a GPU against the CPU (benchmarks/generation/gpu_check.py)",
        "",
        f"`{result['command']}`, {result['finished']}, {result['seconds']:.0f} s in all"
        + (" (stopped early: the tasks below are those done)" if not result.get("complete", True) else "")
        + ".",
        "",
        f"Device {env['device']}: {env['device_name']}{capability}; torch {env['torch']} (CUDA {env['torch_cuda']}, "
        f"cuDNN {env['cudnn']}), numpy {env['numpy']}, Python {env['python']}, {env['cpu_count']} CPUs; torch at "
        f"1 thread and BLAS single-threaded in every task. TF32 by default: matmul "
        f"{env['tf32_default']['matmul_allow_tf32']}, cuDNN {env['tf32_default']['cudnn_allow_tf32']}.",
        f"Config hash {result['config_hash'][:12]}, weights {refiner['weights_id'][:12]}, threshold "
        f"{refiner['threshold']}, preset {refiner['preset']}, poco_version {refiner['poco_version']}. Reference: "
        f"the CPU refiner. First refinement on each (kept out of the times): {warm}.",
        "",
        "R(O) identical: single views and multi-view cases whose refined keys equal the CPU's. Keys differing: in "
        "one R(O) only, summed over the task; max / mean: of |R_cpu xor R| / |R_cpu or R| per refined "
        "observation. Labels differing: samples whose label views or status differ. Times: wall seconds of the "
        "whole task, its refinement steps in brackets.",
        "",
        "| object | rot | variant | views identical | cases identical | keys differing | max | mean | max abs dp "
        "| labels differing | task s (refine s) | cpu task s (refine s) | cpu / variant |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for task in result["tasks"]:
        base = task["runs"][REFERENCE]
        for label in labels:
            head = f"| {task['object']} | {task['rotation']} | {label} |"
            if label in task["errors"]:
                out.append(f"{head} **error**: {task['errors'][label].splitlines()[-1]} |" + " |" * 9)
                continue
            c, run = task["comparisons"][label], task["runs"][label]
            out.append(
                f"{head} {c['singles_identical']}/{c['singles']} | {c['cases_identical']}/{c['cases']} "
                f"| {c['differing_keys']} | {100 * c['share_max']:.3f} % | {100 * c['share_mean']:.4f} % "
                f"| {c['max_prob_diff']:.2e} | {c['labels_differing']}/{c['samples']} "
                f"| {run['task_seconds']:.2f} ({run['refine_seconds']:.2f}) "
                f"| {base['task_seconds']:.2f} ({base['refine_seconds']:.2f}) "
                f"| {base['task_seconds'] / max(run['task_seconds'], 1e-9):.2f}x |"
            )
    out += [
        "",
        "| variant | tasks R(O) identical | tasks labels identical | errors | keys differing / in either | max share "
        "| max abs dp | labels differing | task s | cpu task s | refine s | cpu refine s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, s in result["summary"].items():
        out.append(
            f"| {label} | {s['refined_identical_tasks']}/{s['tasks']} | {s['labels_identical_tasks']}/{s['tasks']} "
            f"| {s['errors']} | {s['differing_keys']} / {s['union_keys']} | {100 * s['share_max']:.3f} % "
            f"| {s['max_prob_diff']:.2e} | {s['labels_differing']}/{s['samples']} | {s['task_seconds']:.1f} "
            f"| {s['reference_task_seconds']:.1f} | {s['refine_seconds']:.1f} | {s['reference_refine_seconds']:.1f} |"
        )
    return "\n".join(out) + "\n"
