"""``<root>/experiment.yaml``: an experiment's name, the commands that made it and its reference line."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import yaml

EXPERIMENT_FILE = "experiment.yaml"


@dataclass(frozen=True)
class Reference:
    """A controller's total reward drawn as a horizontal line beside the learning curves (the autopilot of Fig. 3)."""

    name: str
    total: float

    def to_dict(self) -> dict[str, str | float]:
        """``{name, return}``, as ``experiment.yaml`` and ``tables.json`` hold it."""
        return {"name": self.name, "return": self.total}


@dataclass(frozen=True)
class ExperimentRecord:
    """What ``experiment.yaml`` holds: ``{name, commands, reference: {name, return}}``, each optional."""

    name: str | None = None
    commands: list[str] = field(default_factory=list)
    reference: Reference | None = None

    @classmethod
    def read(cls, root: str | os.PathLike) -> ExperimentRecord:
        """The record of an experiment directory; an empty one without ``experiment.yaml``."""
        path = Path(root) / EXPERIMENT_FILE
        if not path.is_file():
            return cls()
        record = yaml.safe_load(path.read_text()) or {}
        if not isinstance(record, dict):
            raise ValueError(f"{path}: expected a mapping with 'name' and 'commands', got {type(record).__name__}")
        reference = record.get("reference")
        if reference is not None and not (isinstance(reference, dict) and {"name", "return"} <= set(reference)):
            raise ValueError(f"{path}: 'reference' must be a mapping with 'name' and 'return', got {reference!r}")
        name = record.get("name")
        return cls(
            name=None if name is None else str(name),
            commands=[str(c) for c in record.get("commands") or []],
            reference=None if reference is None else Reference(str(reference["name"]), float(reference["return"])),
        )

    def write(self, root: str | os.PathLike) -> Path:
        """Write ``experiment.yaml`` into ``root`` (its keys only where set); its path."""
        record: dict[str, object] = {"commands": self.commands}
        if self.name is not None:
            record["name"] = self.name
        if self.reference is not None:
            record["reference"] = self.reference.to_dict()
        path = Path(root) / EXPERIMENT_FILE
        path.write_text(yaml.safe_dump(record, allow_unicode=True))
        return path

    def with_reference(self, reference: Reference) -> ExperimentRecord:
        """The same record with ``reference`` set."""
        return replace(self, reference=reference)
