"""JSON Schema export for the deployment file, so editors can validate YAML as it is typed."""

from __future__ import annotations

import json
from typing import Any

from openral_core.environment import RobotEnvironment


def robot_environment_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of ``RobotEnvironment``."""
    schema = RobotEnvironment.model_json_schema(mode="validation")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema.setdefault("title", "RobotEnvironment")
    return schema


def robot_environment_schema_json() -> str:
    """The schema as indented JSON text."""
    return json.dumps(robot_environment_schema(), indent=2, sort_keys=True) + "\n"
