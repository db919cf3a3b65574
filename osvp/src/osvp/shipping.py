"""``osvp ship``: a trained checkpoint made into a planner that ships inside osvp (`osvp.shipped`).

Shipping keeps what plays and what a reader of its card needs: the network, its decoding, the
generation config of its training data and the run's record (options, history, samples), and drops
the optimiser's state (two thirds of a checkpoint). Paths of the machine that trained it are replaced
by the names given, so the file is the same wherever it was made from the same run. The training
card beside it (``NAME.md``) says what it was trained on, how, and what it scored; its sha256 is
printed for `osvp.shipped.SHIPPED`, which checks it before every load.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osvp.architectures import architecture
from osvp.checkpoint import load_checkpoint, save_checkpoint
from osvp.train import file_sha256

DROPPED = ("optimiser", "scheduler")
"""What a planner never reads again once trained."""


@dataclass(frozen=True)
class Shipped:
    path: Path
    card: Path
    sha256: str
    size: int


def ship(
    checkpoint: Path,
    folder: Path,
    name: str,
    data_names: dict[str, str],
    commands: str = "",
    scores: str = "",
) -> Shipped:
    """Write ``folder/NAME.pt`` (slim) and ``folder/NAME.md`` (its card) from ``checkpoint``.
    ``data_names`` maps the run's dataset URLs (its ``--data``, ``--val-data``) to names to record."""
    source = load_checkpoint(checkpoint)
    data = {key: value for key, value in source.data.items() if key not in DROPPED and key not in ("format", "version")}
    training = dict(data["training"])
    options = dict(training["options"])
    training["data"] = _named(str(training.get("data", "")), data_names)
    for key in ("data", "val_data"):
        if options.get(key) is not None:
            options[key] = _named(str(options[key]), data_names)
    training["options"] = options
    data["training"] = training
    path = folder / f"{name}.pt"
    save_checkpoint(path, data)
    digest = file_sha256(path)
    card = folder / f"{name}.md"
    card.write_text(training_card(name, load_checkpoint(path).data, digest, commands, scores))
    return Shipped(path=path, card=card, sha256=digest, size=path.stat().st_size)


def _named(url: str, names: dict[str, str]) -> str:
    if url in names:
        return names[url]
    return Path(url.rstrip("/")).name or url


def training_card(name: str, data: dict[str, Any], digest: str, commands: str, scores: str) -> str:
    """The card of a shipped planner: what it is, its data and config, the run, its held-out score."""
    training = data["training"]
    options = training["options"]
    history = training.get("history") or []
    best = int(training.get("best_epoch", 0))
    metric = str(training.get("best_metric", ""))
    held_out = history[best - 1].get(metric) if 0 < best <= len(history) else None
    config = data.get("generation_config") or {}
    family = architecture(str(data.get("architecture", "osvp")))
    reads = "the occupancy grid" + (" and the view state" if data["preset"].get("view_state") else "")
    if family.reads != "grid":
        reads = f"the {'observed' if data.get('source') == 'observed' else 'refined'} cloud and the view state"
    steps = f"{options['steps']} steps" if options.get("steps") else "epochs"
    scene = {key: config.get(key) for key in ("voxel_size", "refiner", "rotations", "imaging") if key in config}
    lines = [
        f"# shipped:{name}",
        "",
        f"`datagen evaluate --planner shipped:{name}` plays it; `osvp.shipped` checks the file's sha256 first.",
        "",
        "| | |",
        "|---|---|",
        f"| file | `{name}.pt`, sha256 `{digest}` |",
        f"| network | {family.name} `{data['preset'].get('name', '')}`, target `{options.get('target', 'label')}`, "
        f"reads {reads} |",
        f"| training data | `{training.get('data')}`: {training.get('train_samples')} samples of "
        f"{training.get('train_objects')} objects |",
        f"| validation | `{options.get('val_data') or 'a split of the training data'}`: "
        f"{training.get('val_samples')} samples |",
        f"| config it expects | hash of its data `{str(training.get('config_hash', ''))[:12]}`; "
        + ", ".join(f"{key} {json.dumps(value)}" for key, value in scene.items())
        + " |",
        f"| training | {steps} of batch {options.get('batch_size')} ({len(history)} epochs), learning rate "
        f"{options.get('learning_rate')}, seed {options.get('seed')}; best epoch {best} |",
        f"| held out | {metric} {held_out:.4f} |" if isinstance(held_out, float) else f"| held out | {metric} |",
        f"| started from | {'sha256 `' + str(options['init']) + '`' if options.get('init') else 'random weights'} |",
    ]
    if commands:
        lines += ["", "## Commands", "", "```bash", commands.strip(), "```"]
    if scores:
        lines += ["", "## Scores", "", scores.strip()]
    return "\n".join(lines) + "\n"
