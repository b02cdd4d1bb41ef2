"""Each ``TickResult`` field names its span attribute and dataset column once; every renderer agrees with it.

A tick attribute or column added anywhere but on the field fails here, and so does a context
attribute whose type drifts from its field's.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import pytest

from openral_core import TickResult
from openral_core.results import DatasetColumn, SpanAttribute, tick_fields_with
from openral_observability import semconv
from openral_runner import tick_context
from openral_runner.tick_context import TickContext

pytest.importorskip("pyarrow", reason="needs the 'dataset' extra")
from openral_dataset import schema

NOT_TICK_FIELDS = {semconv.ATTR_SKILL_ID, semconv.ATTR_DEADLINE_POLICY}
"""Attributes in the tick's namespaces that describe the runner, not one tick."""


@pytest.mark.parametrize("marker", [SpanAttribute, DatasetColumn])
def test_every_field_declares_at_most_one_of_each(marker: type) -> None:
    for name, info in TickResult.model_fields.items():
        assert sum(isinstance(item, marker) for item in info.metadata) <= 1, name


def test_the_span_table_is_the_fields_declarations_and_nothing_else() -> None:
    declared = {name: attribute.name for name, attribute in tick_fields_with(SpanAttribute).items()}
    assert dict(semconv.TICK_ATTRIBUTES) == declared
    assert len(set(declared.values())) == len(declared), "two fields share a span attribute"
    tick_namespace = ("skill.", "openral.tick.", "openral.takeover.")
    by_hand = {
        f"{constant} = {value}"
        for constant, value in vars(semconv).items()
        if constant.startswith("ATTR_") and isinstance(value, str) and value.startswith(tick_namespace)
        if value not in declared.values() and value not in NOT_TICK_FIELDS
    }
    assert by_hand == set(), "a tick attribute written in semconv instead of on its TickResult field"


def test_the_tick_columns_are_the_fields_declarations_and_nothing_else() -> None:
    declared = tick_fields_with(DatasetColumn)
    columns = {c.tick_field: c for c in (*schema.TICK_COLUMNS, *schema.TAKEOVER_COLUMNS)}
    assert list(columns) == list(declared)
    for name, column in columns.items():
        assert column.dtype == declared[name].dtype, name
        assert column.column == (declared[name].name or f"openral.{name}"), name
        assert (name in {c.tick_field for c in schema.TAKEOVER_COLUMNS}) is declared[name].takeover
    assert len({c.column for c in columns.values()}) == len(columns), "two fields share a column"
    cameras = [schema.CameraSpec("front", 8, 6)]
    block = schema.features(["a", "b"], cameras, fps=10, vcodec="h264", takeover=True)
    camera_columns = {schema.camera_column("front", what) for what in ("stamp_ns", "seq", "age_ms", "repeated")}
    by_hand = {key for key in block if key.startswith("openral.")} - {c.column for c in columns.values()}
    assert by_hand == {schema.TRACE_ID, schema.SPAN_ID, *camera_columns}, "a column not declared on its field"


def test_the_recorded_columns_keep_the_names_order_and_dtypes_datasets_were_recorded_with() -> None:
    # A recording resumes only if its features are this recording's: a renamed, retyped or moved column would refuse it.
    def scalar(dtype: str) -> dict[str, object]:
        return {"dtype": dtype, "shape": [1], "names": None}

    actions = {"dtype": "float32", "shape": [2], "names": ["a", "b"]}
    recorded_before = {
        "openral.tick_idx": scalar("int64"),
        "openral.tick_start_ns": scalar("int64"),
        "openral.lateness_ms": scalar("float32"),
        "openral.action_applied": scalar("bool"),
        "openral.withheld_reason": scalar("string"),
        "openral.requested_action": actions,
        "openral.intervention": scalar("bool"),
        "openral.active_skill": scalar("string"),
        "openral.policy_action": actions,
        "openral.handover_ramp": scalar("bool"),
        "openral.trace_id": scalar("string"),
        "openral.span_id": scalar("string"),
    }
    block = schema.features(["a", "b"], [], fps=10, vcodec="h264", takeover=True)
    assert [(key, spec) for key, spec in block.items() if key.startswith("openral.")] == list(recorded_before.items())


def test_the_context_carries_result_fields_under_their_names_and_types() -> None:
    carried = {f.name for f in fields(TickContext)} & set(TickResult.model_fields)
    built = set(tick_context._BUILT_HERE)
    defaulted = {name for name, _ in tick_context._DEFAULTED}
    assert built <= set(TickResult.model_fields), "result() builds a field TickResult does not have"
    assert carried | built | defaulted == set(TickResult.model_fields)
    assert not carried & built
    assert not carried & defaulted
    assert not built & defaulted


def test_a_context_attribute_of_another_type_than_its_field_is_refused() -> None:
    @dataclass
    class Drifted(TickContext):
        sensors_ms: int = 0  # type: ignore[assignment]

    with pytest.raises(TypeError, match=r"Drifted\.sensors_ms is <class 'int'>, but TickResult\.sensors_ms"):
        tick_context._split(Drifted)


def test_a_context_that_carries_a_field_result_builds_is_refused() -> None:
    @dataclass
    class Doubled(TickContext):
        tick_ms: float = 0.0

    with pytest.raises(TypeError, match=r"TickResult\.tick_ms is built by TickContext\.result\(\)"):
        tick_context._split(Doubled)
