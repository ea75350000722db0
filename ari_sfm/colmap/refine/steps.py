"""refine-colmap's step results as frozen records: a start distance tried by the search, a block of a long
chain's sliding start, a restart. Each reads as the mapping refine.json writes (``step["cost"]``,
``dict(step) == step.to_json()``), and its counts are fields summed by name, not keys of a dict."""
from __future__ import annotations

from abc import abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any


class StepRecord(Mapping[str, Any]):
    """A step result that also reads as its JSON mapping (the keys of :meth:`to_json`)."""

    @abstractmethod
    def to_json(self) -> dict[str, Any]:
        """The record as refine.json (or the log) holds it."""

    def __getitem__(self, key: str) -> Any:
        """The JSON value of ``key``."""
        return self.to_json()[key]

    def __iter__(self) -> Iterator[str]:
        """The JSON keys."""
        return iter(self.to_json())

    def __len__(self) -> int:
        """How many JSON keys."""
        return len(self.to_json())


@dataclass(frozen=True)
class SearchStep(StepRecord):
    """One start distance of the distance search: LM with the window held (refine.json ``distance_search``)."""

    distance_mm: float
    cost: float
    iterations: int
    linearizations: int
    observations: int  # of the subset it ran on (or of every point: the best distance again)

    def to_json(self) -> dict[str, Any]:
        """refine.json's ``distance_search`` entry."""
        return {"distance_mm": self.distance_mm, "cost": self.cost, "iterations": self.iterations,
                "linearizations": self.linearizations, "observations": self.observations}


@dataclass(frozen=True)
class BlockStep(StepRecord):
    """One block of a long chain's sliding start (:func:`~ari_sfm.colmap.refine.chain_start.slid_start`)."""

    frames: int
    held: int  # of its frames, those held (refined before)
    points3D: int  # noqa: N815 (the COLMAP name)
    cost: float
    iterations: int
    linearizations: int
    dropped: bool = False  # ended too far above the first block's cost per observation: taken again, shorter

    def to_json(self) -> dict[str, Any]:
        """The block's figures (``dropped`` only when it was)."""
        out: dict[str, Any] = {"frames": self.frames, "held": self.held, "points3D": self.points3D,
                               "cost": self.cost, "iterations": self.iterations,
                               "linearizations": self.linearizations}
        if self.dropped:
            out["dropped"] = True
        return out


@dataclass(frozen=True)
class RestartStep(StepRecord):
    """Another start refined when the distance ran toward 0 (refine.json ``restarts``: distance and cost)."""

    distance_mm: float
    cost: float
    iterations: int
    linearizations: int

    def to_json(self) -> dict[str, Any]:
        """refine.json's ``restarts`` entry."""
        return {"distance_mm": self.distance_mm, "cost": self.cost}
