"""Run one of the authors' training scripts unchanged, as ``python SCRIPT ARGS`` would, with help that touches
none of their files, and a probe of what it read and what its loss was.

    python launch.py --script DIR/train.py [--set-module config.NUM_EPOCHS=1] [--set-global epochs=1]
                     [--probe OUT.json] [--preload MODULE] -- ARGS...

- ``--set-module MOD.NAME=JSON``: import their module MOD (from the script's folder, as the script
  would) and set one of its globals before the script runs; the script's own ``import MOD`` then gets
  the same module (how MA-SCVP's ``config.py`` is given the data path and one epoch).
- ``--set-global NAME=JSON``: the script assigns NAME at its top level (NBVNet's ``epochs = 1000``);
  right after that assignment the value is replaced, by a trace function on the script's module frame
  alone, which is removed as soon as every such name is set.
- ``--preload MODULE``: import a module first (a diagnostic patch; a run that uses one is not a run of
  their code unmodified, and the driver labels it so).
- ``--probe OUT.json``: records, without changing what is computed, every DataLoader the script
  iterates (its dataset class and length, the batches and samples it yields, the shapes and dtypes of
  the first batch) and the value of every scalar tensor ``backward()`` is called on (the training
  loss), plus which CUDA-only extension modules were ever imported.

The script's folder comes first on ``sys.path`` and ``sys.argv`` is ``[SCRIPT, *ARGS]``, as for a plain
``python SCRIPT``. Only the standard library and torch are used; no module of the repository is imported.
"""

from __future__ import annotations

import argparse
import importlib
import json
import runpy
import sys
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

CUDA_EXTENSIONS = ("pointnet2_cuda", "pointnet2", "emd", "chamfer", "chamfer_distance", "cd", "pointnet2_ops")
"""Compiled extensions of PC-NBV's and PoinTr's trees that a CPU machine cannot build."""


def _pair(text: str) -> tuple[str, Any]:
    name, _, value = text.partition("=")
    if not name or not _:
        raise argparse.ArgumentTypeError(f"{text!r}: give NAME=JSON")
    return name, json.loads(value)


def _describe(value: Any) -> Any:
    """Shapes and dtypes of the tensors and arrays in a batch (tuples, lists and dicts walked)."""
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return {"shape": [int(n) for n in value.shape], "dtype": str(value.dtype).replace("torch.", "")}
    if isinstance(value, dict):
        return {str(k): _describe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_describe(v) for v in value]
    return type(value).__name__


def _batch_size(value: Any) -> int:
    if hasattr(value, "shape") and len(value.shape):
        return int(value.shape[0])
    if isinstance(value, dict):
        return _batch_size(next(iter(value.values())))
    if isinstance(value, (list, tuple)) and value:
        return _batch_size(value[0])
    return 0


class Probe:
    """What the script read and what it minimised, gathered while it runs."""

    def __init__(self) -> None:
        self.loaders: dict[int, dict[str, Any]] = {}
        self.losses: list[float] = []

    def install(self) -> None:
        import torch
        from torch.utils.data import DataLoader

        probe = self
        iterate = DataLoader.__iter__

        def probing_iter(loader: Any) -> Iterator[Any]:
            record = probe.loaders.setdefault(
                id(loader),
                {
                    "dataset": type(loader.dataset).__name__,
                    "dataset_len": len(loader.dataset),
                    "sampler": type(loader.sampler).__name__,
                    "batch_size": loader.batch_size,
                    "passes": 0,
                    "batches": 0,
                    "samples": 0,
                    "first_batch": None,
                },
            )
            record["passes"] += 1
            for batch in iterate(loader):
                if record["first_batch"] is None:
                    record["first_batch"] = _describe(batch)
                record["batches"] += 1
                record["samples"] += _batch_size(batch)
                yield batch

        backward = torch.Tensor.backward

        def probing_backward(tensor: Any, *args: Any, **kwargs: Any) -> Any:
            if tensor.numel() == 1:
                probe.losses.append(float(tensor.detach().reshape(())))
            return backward(tensor, *args, **kwargs)

        DataLoader.__iter__ = probing_iter  # type: ignore[assignment,method-assign]
        torch.Tensor.backward = probing_backward  # type: ignore[method-assign]

    def report(self, outcome: dict[str, Any]) -> dict[str, Any]:
        return {
            **outcome,
            "loaders": list(self.loaders.values()),
            "losses": self.losses,
            "cuda_extensions_imported": sorted(name for name in CUDA_EXTENSIONS if name in sys.modules),
        }


def _override_after_assignment(script: str, values: dict[str, Any]) -> None:
    """Set each NAME of ``values`` in the script's globals right after the script first assigns it."""
    pending = dict(values)

    def on_line(frame: Any, event: str, arg: Any) -> Any:
        if event == "line":
            for name in [n for n in pending if n in frame.f_globals]:
                frame.f_globals[name] = pending.pop(name)
            if not pending:
                frame.f_trace = None
                sys.settrace(None)
                return None
        return on_line

    def on_call(frame: Any, event: str, arg: Any) -> Any:
        if frame.f_code.co_filename == script and frame.f_code.co_name == "<module>":
            return on_line
        return None

    if pending:
        sys.settrace(on_call)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--script", required=True, type=Path)
    parser.add_argument("--set-module", action="append", type=_pair, default=[], metavar="MOD.NAME=JSON")
    parser.add_argument("--set-global", action="append", type=_pair, default=[], metavar="NAME=JSON")
    parser.add_argument("--probe", type=Path)
    parser.add_argument("--preload", action="append", default=[], metavar="MODULE", help="Import it first.")
    parser.add_argument("args", nargs=argparse.REMAINDER)
    options = parser.parse_args()
    script = str(options.script.resolve())
    args = options.args[1:] if options.args[:1] == ["--"] else options.args
    sys.argv = [script, *args]
    sys.path.insert(0, str(Path(script).parent))
    probe = Probe()
    if options.probe is not None:
        probe.install()
    for dotted, value in options.set_module:
        module_name, _, name = dotted.rpartition(".")
        setattr(importlib.import_module(module_name), name, value)
    for name in options.preload:
        importlib.import_module(name)
    outcome: dict[str, Any] = {"exit": 0, "error": None, "preloaded": options.preload}
    _override_after_assignment(script, dict(options.set_global))
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as stop:
        outcome["exit"] = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except BaseException as exc:
        traceback.print_exc()
        outcome["exit"] = 1
        outcome["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        sys.settrace(None)
        if options.probe is not None:
            options.probe.write_text(json.dumps(probe.report(outcome), indent=1) + "\n")
    return int(outcome["exit"])


if __name__ == "__main__":
    raise SystemExit(main())
