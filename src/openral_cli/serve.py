"""``openral serve``: run a policy on this machine (the one with the GPU) for robots elsewhere, over Zenoh."""

from __future__ import annotations

import importlib
import threading
from pathlib import Path
from typing import Any

import click

from openral_cli.errors import exit_codes
from openral_cli.options import json_object
from openral_cli.session import command_span
from openral_cli.signals import StopSignals
from openral_core import RobotManifest, ROSConfigError, SimEnvironment
from openral_hal.manifests import load_robot_manifest
from openral_observability.setup import PROTOCOLS
from openral_remote.allocator import keep_message_memory
from openral_remote.config import DEFAULT_SERVER_LISTEN, ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import describe, model_hash
from openral_rskill.base import RSkillBase
from openral_runner.factory import SKILL_REGISTRY


def _robot_and_rate(
    robot_id: str | None, scene_path: Path | None, rate_hz: float | None
) -> tuple[RobotManifest, float]:
    """The robot the policy is built for: a manifest, or a simulation scene's action space and rate."""
    if scene_path is not None:
        if robot_id is not None:
            raise ROSConfigError("give --robot or --scene, not both", field="--robot")
        scene = SimEnvironment.from_yaml(scene_path)
        make_env = importlib.import_module("openral_sim.env").make_env  # the simulators: the 'sim' extras
        env = make_env(scene)
        try:
            spec = env.spec
        finally:
            env.close()
        return spec.action_manifest(scene.robot or scene.env), rate_hz or scene.rate_hz or spec.control_hz
    return load_robot_manifest(robot_id or "so101_follower"), rate_hz or 30.0


@click.command()
@click.option("--skill", "skill_id", required=True, help="The policy to serve (an openral.skills id).")
@click.option("--skill-params", default=None, help="Its parameters as a JSON object.")
@click.option("--robot", "robot_id", default=None, help="Robot manifest id it acts for (default so101_follower).")
@click.option(
    "--scene",
    "scene_path",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="Serve for a simulation scene's action space instead of a robot.",
)
@click.option("--rate-hz", type=click.FloatRange(min=0, min_open=True), default=None, help="The robot's loop rate.")
@click.option("--name", default=None, help="The policy's name in its key (default: the skill id).")
@click.option(
    "--listen",
    multiple=True,
    metavar="ENDPOINT",
    help=f"Zenoh endpoint to listen on (repeatable; default {DEFAULT_SERVER_LISTEN}).",
)
@click.option("--connect", multiple=True, metavar="ENDPOINT", help="Zenoh endpoint to connect to (a router).")
@click.option("--lease-ms", type=click.IntRange(100, 60_000), default=1000, show_default=True)
@click.option("--otlp-endpoint", metavar="URL", default=None, help="Export traces and metrics over OTLP.")
@click.option("--otlp-protocol", type=click.Choice(PROTOCOLS), default=None)
@click.pass_context
def serve(
    ctx: click.Context,
    *,
    skill_id: str,
    skill_params: str | None,
    robot_id: str | None,
    scene_path: Path | None,
    rate_hz: float | None,
    name: str | None,
    listen: tuple[str, ...],
    connect: tuple[str, ...],
    lease_ms: int,
    otlp_endpoint: str | None,
    otlp_protocol: str | None,
) -> None:
    """Serve a policy on openral/<robot>/policy/<name>/{infer,meta,reset} until Ctrl-C.

    The liveliness token openral/<robot>/policy/<name>/alive is declared once the policy has
    warmed up; robots running the remote_policy skill wait for it. The link is neither
    authenticated nor encrypted unless Zenoh's TLS/authentication is configured around it: serve
    on a network you trust.
    """
    with StopSignals() as signals, exit_codes(bool(ctx.obj["debug"])):
        params = json_object(skill_params, "--skill-params")
        zenoh = ZenohConfig(
            mode="peer",
            listen=list(listen) or ([] if connect else [DEFAULT_SERVER_LISTEN]),
            connect=list(connect),
            lease_ms=lease_ms,
        )
        # Loaded only here: the Zenoh server imports eclipse-zenoh (the 'remote' extra).
        server_module = importlib.import_module("openral_remote.server")
        keep_message_memory()  # this process moves camera-sized messages: glibc keeps their memory for reuse
        robot, rate = _robot_and_rate(robot_id, scene_path, rate_hz)
        keys = PolicyKeys.of(robot.robot_id, name or skill_id)
        with command_span(
            "serve",
            scene_path or Path(keys.prefix),
            otlp_endpoint=otlp_endpoint,
            otlp_protocol=otlp_protocol,
            trace_sample_ratio=None,
        ):
            skill: RSkillBase = SKILL_REGISTRY.resolve(skill_id, field="--skill").from_config(
                params, robot=robot, rate_hz=rate
            )
            meta = describe(
                skill,
                policy=keys.policy,
                robot=robot.robot_id,
                action_names=robot.joint_names,
                rate_hz=rate,
                model_hash=model_hash(skill_id, params, Path.cwd()),
            )
            stopped = threading.Event()
            signals.on_stop(lambda _reason: stopped.set())
            server: Any = server_module.PolicyServer(skill, keys=keys, zenoh=zenoh, meta=meta)
            with server:
                click.echo(
                    f"serving {keys.prefix} ({skill_id}, chunk {meta.chunk_size}, model {meta.model_hash[:12]}, "
                    f"warm-up {server.meta.warmup_ms:.0f} ms) on {', '.join(zenoh.listen or zenoh.connect)}",
                    err=True,
                )
                stopped.wait()
            stats = server.stats
            click.echo(
                f"served {stats.served}, superseded {stats.superseded}, errors {stats.errors}, resets {stats.resets}",
                err=True,
            )
