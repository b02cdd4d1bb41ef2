"""The tick telemetry fast path reads SDK internals: only for the SDK releases it was checked against."""

from __future__ import annotations

import subprocess
import sys
from importlib import metadata

import pytest
from opentelemetry.sdk.trace import TracerProvider

from openral_observability import span_pipeline
from openral_observability.span_pipeline import SDK_RELEASES_READ, SdkSpanPipeline, sdk_release_supported


def test_the_locked_sdk_is_a_release_whose_internals_were_checked() -> None:
    release = ".".join(metadata.version("opentelemetry-sdk").split(".")[:2])
    assert release in SDK_RELEASES_READ, (
        f"opentelemetry-sdk {release} is installed: check span_pipeline.py (Tracer.sampler, id_generator, "
        "span_processor, resource, instrumentation_info; ReadableSpan's constructor) against it, then add it "
        "to SDK_RELEASES_READ"
    )
    assert SdkSpanPipeline.of(TracerProvider().get_tracer("probe")) is not None


def test_another_sdk_release_falls_back_to_live_spans(monkeypatch: pytest.MonkeyPatch) -> None:
    sdk_release_supported.cache_clear()
    monkeypatch.setattr(metadata, "version", lambda _name: "9.1.0")
    try:
        with pytest.warns(RuntimeWarning, match="opentelemetry-sdk 9.1"):
            assert SdkSpanPipeline.of(TracerProvider().get_tracer("probe")) is None
    finally:
        monkeypatch.undo()
        sdk_release_supported.cache_clear()
    assert span_pipeline.sdk_release_supported()


def test_the_export_process_does_not_import_setup() -> None:
    code = "import sys, openral_observability.export_process; print('openral_observability.setup' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.strip() == "False", "setup imports the export process, never the other way round"
