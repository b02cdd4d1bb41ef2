"""JSON Schema of the files users write (deployments, scenes, suites), so editors validate YAML as it is typed."""

from __future__ import annotations

import json
from typing import Any

from pydantic import BaseModel

from openral_core.environment import RobotEnvironment
from openral_core.sim import BenchmarkSuite, SimEnvironment

FILE_MODELS: dict[str, type[BaseModel]] = {
    "deployment": RobotEnvironment,
    "scene": SimEnvironment,
    "suite": BenchmarkSuite,
}
"""Each kind of configuration file and the model that validates it."""


def model_schema(model: type[BaseModel]) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a configuration model."""
    schema = model.model_json_schema(mode="validation")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema.setdefault("title", model.__name__)
    return schema


def robot_environment_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of ``RobotEnvironment``."""
    return model_schema(RobotEnvironment)


def sim_environment_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of ``SimEnvironment`` (a scene file)."""
    return model_schema(SimEnvironment)


def schema_json(kind: str = "deployment") -> str:
    """The schema of one kind of file as indented JSON text."""
    return json.dumps(model_schema(FILE_MODELS[kind]), indent=2, sort_keys=True) + "\n"


def robot_environment_schema_json() -> str:
    """The deployment schema as indented JSON text."""
    return schema_json("deployment")
