"""Telemetry configuration: arguments and OTEL_* variables resolve to what setup() installs, or to nothing."""

from __future__ import annotations

from typing import Any

import pytest

from openral_core import ROSConfigError
from openral_observability.telemetry_config import PROTOCOL_GRPC, PROTOCOL_HTTP, resolve_config

HTTP = "http://collector:4318"


def test_nothing_configured_resolves_to_nothing() -> None:
    assert resolve_config(env={}) is None
    assert resolve_config(protocol=PROTOCOL_GRPC, sample_ratio=0.5, env={}) is None
    assert resolve_config(endpoint=HTTP, env={"OTEL_SDK_DISABLED": "true"}) is None
    disabled = {f"OTEL_{s}_EXPORTER": "none" for s in ("TRACES", "METRICS", "LOGS")}
    assert resolve_config(endpoint=HTTP, env=disabled) is None


def test_explicit_http_endpoint_gets_the_signal_paths() -> None:
    config = resolve_config(endpoint=HTTP + "/", sample_ratio=0.25, env={})
    assert config is not None
    assert dict(config.endpoints) == {s: f"{HTTP}/v1/{s}" for s in ("traces", "metrics", "logs")}
    assert set(config.protocols.values()) == {PROTOCOL_HTTP}
    assert config.sample_ratio == 0.25
    assert config.service_name == "openral"


def test_grpc_endpoint_is_used_as_is() -> None:
    config = resolve_config(endpoint="http://collector:4317", protocol=PROTOCOL_GRPC, env={})
    assert config is not None
    assert set(config.endpoints.values()) == {"http://collector:4317"}
    assert set(config.protocols.values()) == {PROTOCOL_GRPC}


def test_environment_endpoints_are_left_to_the_exporters() -> None:
    config = resolve_config(
        env={
            "OTEL_EXPORTER_OTLP_TRACES_ENDPOINT": "http://t:4318/v1/traces",
            "OTEL_EXPORTER_OTLP_PROTOCOL": "grpc",
            "OTEL_EXPORTER_OTLP_TRACES_PROTOCOL": "http/protobuf",
            "OTEL_SERVICE_NAME": "arm-7",
        }
    )
    assert config is not None
    assert dict(config.endpoints) == {"traces": None}  # only the signal with an endpoint is exported
    assert dict(config.protocols) == {"traces": PROTOCOL_HTTP}  # the per-signal variable wins
    assert config.service_name is None  # the SDK reads OTEL_SERVICE_NAME itself
    config = resolve_config(env={"OTEL_EXPORTER_OTLP_ENDPOINT": HTTP, "OTEL_LOGS_EXPORTER": "none"})
    assert config is not None
    assert set(config.endpoints) == {"traces", "metrics"}


@pytest.mark.parametrize(
    ("kwargs", "env", "field"),
    [
        ({"protocol": "http/json"}, {}, "otlp_protocol"),
        ({}, {"OTEL_EXPORTER_OTLP_PROTOCOL": "thrift"}, "otlp_protocol"),
        ({"sample_ratio": 1.5}, {}, "trace_sample_ratio"),
        ({}, {"OTEL_TRACES_EXPORTER": "zipkin"}, "OTEL_TRACES_EXPORTER"),
    ],
)
def test_bad_settings_are_config_errors(kwargs: dict[str, Any], env: dict[str, str], field: str) -> None:
    with pytest.raises(ROSConfigError) as info:
        resolve_config(endpoint=HTTP, env=env, **kwargs)
    assert info.value.field == field
