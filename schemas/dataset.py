"""``dataset.json``: what a dataset is, readable without the pipeline."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, field_validator

from schemas.config import RECORDED, GenerationConfig, stored_config

DATASET_FILE = "dataset.json"
CARD_FILE = "README.md"
"""The dataset card (`datagen shards card`) at a dataset's root; `shards export` copies it."""


class DatasetInfo(BaseModel):
    """The generation config and its hash, the view space, the camera and the software versions."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_version: int
    config: GenerationConfig
    config_hash: str
    view_positions: list[tuple[float, float, float]]
    """The n candidate view positions (metres, task frame); bit i of a mask is view i."""
    versions: dict[str, str]
    created: str
    """ISO 8601 time the dataset was first written."""

    @field_validator("config", mode="before")
    @classmethod
    def _as_recorded(cls, value: Any) -> Any:
        """A dataset keeps the config it was made with: fields it predates read as what reproduces it,
        and a plug-in's refiner or objective is taken by name where the plug-in is not installed."""
        if isinstance(value, GenerationConfig):
            return value
        return GenerationConfig.model_validate(stored_config(value), context=RECORDED)

    @property
    def num_views(self) -> int:
        return len(self.view_positions)

    def summary(self) -> dict[str, Any]:
        return {
            "schema_version": self.schema_version,
            "config_hash": self.config_hash,
            "views": self.num_views,
        }


PACK_BYTES = 512 * 1024**2
"""About how large each tar file of a packed dataset is, by default (`storage.dataset.pack`, ``--pack-mb``)."""
