"""ChunkBuffer: rows indexed by tick, skipping, refusing, seams and ensembles, with no thread and no clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openral_core import ExecutorConfig, SeamMode
from openral_rskill.chunk_buffer import ChunkBuffer


def chunk(obs_tick: int, rows: int = 6) -> np.ndarray:
    """Row j of a chunk observed at tick k is [k * 100 + j, -j]: each value names its tick."""
    return np.array([[obs_tick * 100 + j, -j] for j in range(rows)], dtype=float)


def buffer(**options: object) -> ChunkBuffer:
    return ChunkBuffer(2, ExecutorConfig.model_validate(options))


def test_rows_for_ticks_already_past_are_skipped_and_each_row_serves_its_own_tick() -> None:
    buf = buffer()
    placed = buf.place(chunk(10), obs_tick=10, tick=13)
    assert (placed.skipped, placed.used, placed.refused) == (3, 3, False)
    assert buf.base_tick == 13
    row = buf.row_for(13)
    assert row is not None
    assert row.tolist() == [1003.0, -3.0]
    assert buf.ahead(13) == 3


def test_reading_a_later_tick_drops_the_rows_before_it_and_a_tick_past_the_end_empties_the_buffer() -> None:
    buf = buffer()
    buf.place(chunk(0, rows=5), obs_tick=0, tick=0)
    row = buf.row_for(3)
    assert row is not None
    assert row[0] == 3.0
    assert (buf.base_tick, len(buf)) == (3, 2)
    assert buf.row_for(2) is None  # a tick before the buffer's first: nothing, and nothing dropped
    assert len(buf) == 2
    assert buf.row_for(5) is None
    assert len(buf) == 0
    assert buf.ahead(5) == 0


def test_rows_from_is_what_runs_from_a_tick_on() -> None:
    buf = buffer()
    buf.place(chunk(0, rows=4), obs_tick=0, tick=0)
    np.testing.assert_array_equal(buf.rows_from(2)[:, 0], [2.0, 3.0])
    np.testing.assert_array_equal(buf.rows_from(-1)[:, 0], [0.0, 1.0, 2.0, 3.0])  # before the first: all of them
    assert buf.rows_from(9).shape == (0, 2)


def test_a_chunk_with_fewer_usable_rows_than_min_rows_is_refused_and_changes_nothing() -> None:
    buf = buffer(min_rows=2)
    buf.place(chunk(0), obs_tick=0, tick=0)
    placed = buf.place(chunk(1, rows=4), obs_tick=1, tick=4)  # one row left, for tick 4
    assert placed.refused
    assert placed.skipped == 3
    row = buf.row_for(4)
    assert row is not None
    assert row[0] == 4.0  # still the first chunk's row


def test_executed_rows_caps_each_chunk_before_skipping() -> None:
    buf = buffer(executed_rows=3)
    placed = buf.place(chunk(0), obs_tick=0, tick=1)
    assert (placed.skipped, placed.used) == (1, 2)
    assert buf.ahead(1) == 2


def test_stale_start_runs_a_chunk_from_its_first_row_however_late() -> None:
    buf = buffer(indexing="stale_start")
    placed = buf.place(chunk(0), obs_tick=0, tick=4)
    assert (placed.skipped, placed.used) == (0, 6)
    row = buf.row_for(4)
    assert row is not None
    assert row[0] == 0.0


def test_replace_takes_the_new_rows_from_the_tick_of_placing_and_ends_where_they_end() -> None:
    buf = buffer(seam=SeamMode.REPLACE)
    buf.place(chunk(0, rows=8), obs_tick=0, tick=0)
    buf.place(chunk(2, rows=3), obs_tick=2, tick=2)
    assert [buf.row_for(t)[0] for t in (2, 3, 4)] == [200.0, 201.0, 202.0]  # type: ignore[index]
    assert buf.row_for(5) is None


def test_crossfade_blends_the_old_rows_into_the_new_over_crossfade_rows() -> None:
    buf = buffer(seam=SeamMode.CROSSFADE, crossfade_rows=2)
    buf.place(chunk(0), obs_tick=0, tick=0)
    buf.place(chunk(2, rows=4), obs_tick=2, tick=2)
    values = [buf.row_for(t)[0] for t in (2, 3, 4, 5)]  # type: ignore[index]
    # alpha 1/3 then 2/3 towards the new chunk, then the new chunk alone.
    assert values == pytest.approx([2 / 3 * 2 + 1 / 3 * 200, 1 / 3 * 3 + 2 / 3 * 201, 202.0, 203.0])


def test_crossfade_into_an_empty_buffer_is_the_new_chunk() -> None:
    buf = buffer(seam=SeamMode.CROSSFADE)
    buf.place(chunk(0, rows=3), obs_tick=0, tick=0)
    np.testing.assert_array_equal(buf.rows_from(0), chunk(0, rows=3))


def test_ensemble_weights_every_prediction_of_a_tick_oldest_first() -> None:
    decay = 0.5
    buf = buffer(seam=SeamMode.ENSEMBLE, ensemble_decay=decay)
    for k in range(3):  # a chunk every tick, each predicting ticks k .. k + 5
        buf.place(chunk(k), obs_tick=k, tick=k)
    # Tick 2 was predicted by the chunks of ticks 0, 1 and 2 (its rows 2, 1 and 0), in that order.
    predictions = [chunk(0)[2], chunk(1)[1], chunk(2)[0]]
    weights = [math.exp(-decay * i) for i in range(3)]
    expected = sum(w * p for w, p in zip(weights, predictions, strict=True)) / sum(weights)
    np.testing.assert_allclose(buf.row_for(2), expected)  # type: ignore[arg-type]
    # Tick 7 only by the newest chunk (its row 5): its own value.
    np.testing.assert_allclose(buf.rows_from(7)[0], chunk(2)[5])


def test_ensemble_forgets_the_predictions_of_dropped_rows_and_of_a_cleared_buffer() -> None:
    buf = buffer(seam=SeamMode.ENSEMBLE, ensemble_decay=0.0)
    buf.place(chunk(0), obs_tick=0, tick=0)
    buf.row_for(3)  # ticks 0..2 dropped
    buf.place(chunk(3, rows=2), obs_tick=3, tick=3)
    np.testing.assert_allclose(buf.rows_from(3)[:, 0], [(3.0 + 300.0) / 2, (4.0 + 301.0) / 2])
    buf.clear()
    assert len(buf) == 0
    buf.place(chunk(9, rows=2), obs_tick=9, tick=9)
    np.testing.assert_allclose(buf.rows_from(9), chunk(9, rows=2))  # nothing of before the clear


def test_rows_placed_from_a_read_only_message_are_never_written() -> None:
    rows = chunk(0)
    rows.flags.writeable = False  # a remote chunk is a view of the received message
    for seam in SeamMode:
        buf = buffer(seam=seam)
        buf.place(rows, obs_tick=0, tick=0)
        buf.place(rows, obs_tick=0, tick=1)
        assert buf.row_for(1) is not None
