"""``ConsoleParams``: what the ``console`` observer entry (``--console [HOST:]PORT``) may set."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

DEFAULT_HOST = "127.0.0.1"
"""Loopback: only this machine can open the console, and no token is needed."""


class ConsoleParams(BaseModel):
    """Parameters of the ``console`` observer in a deployment's ``observers:`` block."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = Field(
        default=DEFAULT_HOST,
        min_length=1,
        description="Interface to bind; any non-loopback address requires the token printed at start.",
    )
    port: int = Field(default=0, ge=0, le=65535, description="Port to serve on (0: any free one, printed at start).")
    update_hz: float = Field(
        default=10.0, gt=0, le=60, description="How often each open page is sent the joints, tick counter and health."
    )
    image_hz: float = Field(
        default=5.0,
        gt=0,
        le=60,
        description="Most camera images per second each page is sent per camera (a browser on the robot's "
        "computer decodes and paints every one: its CPU is the robot's).",
    )
    status_hz: float = Field(
        default=4.0, gt=0, le=30, description="How often the loop's health (rates, jitter, faults) is recomputed."
    )
    history: int = Field(
        default=300, ge=0, le=10_000, description="Joint samples a page receives when it connects (its plots' past)."
    )
    max_clients: int = Field(default=8, ge=1, le=256, description="Pages open at once; one more is refused (503).")
