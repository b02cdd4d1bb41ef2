"""``openral serve``: run a policy on this machine (the one with the GPU) for robots elsewhere, over Zenoh.

The server's Zenoh id is stable (kept per host and key, :mod:`openral_remote.identity`, unless
``--zenoh-id`` gives one), so robots, which pin the server they first reached, take it back after a
restart, while a second server of the key on this host gets another id and so is seen, and refused.
``--tls-*`` put every link behind TLS (``--mtls``: robots need a certificate too; ``--allow``: only
these certificate names are heard); the files are checked before the policy is loaded.
"""

from __future__ import annotations

import importlib
import re
import threading
from pathlib import Path
from typing import Any

import click

from openral_cli.errors import exit_codes
from openral_cli.options import json_object
from openral_cli.serve_limits import limit_options, serve_limits
from openral_cli.session import command_span
from openral_cli.signals import StopSignals
from openral_core import RobotManifest, ROSConfigError, SimEnvironment
from openral_core.config import validate_model
from openral_hal.manifests import load_robot_manifest
from openral_observability.setup import PROTOCOLS
from openral_remote.allocator import keep_message_memory
from openral_remote.config import (
    DEFAULT_SERVER_LISTEN,
    DEFAULT_SERVER_LISTEN_TLS,
    ZENOH_ID,
    TlsConfig,
    ZenohConfig,
)
from openral_remote.identity import claim_server_id
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


def _tls(ca: Path | None, cert: Path | None, key: Path | None, *, mutual: bool) -> TlsConfig | None:
    """The ``--tls-*`` options as one block, its files checked (nothing is loaded or opened before).

    Raises:
        ROSConfigError: An option is missing, or a file is wrong (naming it).
    """
    given = {"--tls-ca": ca, "--tls-cert": cert, "--tls-key": key}
    if not any(given.values()):
        if mutual:
            raise ROSConfigError("--mtls needs TLS", field="--mtls", hint="give --tls-ca, --tls-cert and --tls-key")
        return None
    missing = [option for option, value in given.items() if value is None]
    if missing:
        raise ROSConfigError(
            f"TLS needs {', '.join(missing)} too", field=missing[0], hint="give --tls-ca, --tls-cert and --tls-key"
        )
    tls = TlsConfig(ca=str(ca), cert=str(cert), key=str(key), mutual=mutual)
    check_tls = importlib.import_module("openral_remote.tls").check_tls  # cryptography: the 'remote' extra
    check_tls(tls, prefix="--tls-")
    return tls


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
@click.option(
    "--zenoh-id",
    metavar="HEX",
    default=None,
    help="This server's Zenoh id, which robots pin (default: one kept for the key on this host, "
    "the same at every restart).",
)
@click.option(
    "--tls-ca", type=click.Path(path_type=Path), default=None, help="TLS: the CA certificate that signs every peer's."
)
@click.option("--tls-cert", type=click.Path(path_type=Path), default=None, help="TLS: this server's certificate.")
@click.option("--tls-key", type=click.Path(path_type=Path), default=None, help="TLS: its unencrypted private key.")
@click.option("--mtls", is_flag=True, help="Mutual TLS: a robot needs a certificate signed by the CA too.")
@click.option(
    "--allow",
    multiple=True,
    metavar="NAME",
    help="Certificate common name of a robot that may query (repeatable; needs --mtls). Others are not heard.",
)
@limit_options
@click.option("--otlp-endpoint", metavar="URL", default=None, help="Export traces and metrics over OTLP.")
@click.option("--otlp-protocol", type=click.Choice(PROTOCOLS), default=None)
@click.pass_context
def serve(
    ctx: click.Context,
    /,
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
    zenoh_id: str | None,
    tls_ca: Path | None,
    tls_cert: Path | None,
    tls_key: Path | None,
    mtls: bool,
    allow: tuple[str, ...],
    otlp_endpoint: str | None,
    otlp_protocol: str | None,
    **limit_values: Any,
) -> None:
    """Serve a policy on openral/<robot>/policy/<name>/{infer,meta,reset} until Ctrl-C.

    The liveliness token openral/<robot>/policy/<name>/alive is declared once the policy has
    warmed up; robots running the remote_policy skill wait for it. Without --tls-* the link is
    neither authenticated nor encrypted: serve on a network you trust, or give the TLS files
    (with --mtls and --allow, only the named robots' certificates are heard).
    """
    with StopSignals() as signals, exit_codes(bool(ctx.obj["debug"])):
        params = json_object(skill_params, "--skill-params")
        limits = serve_limits(limit_values)
        if zenoh_id is not None and not re.fullmatch(ZENOH_ID, zenoh_id):
            raise ROSConfigError(
                f"{zenoh_id!r} is not a Zenoh id",
                field="--zenoh-id",
                hint="lowercase hex, 1 to 32 digits, no leading 0",
            )
        tls = _tls(tls_ca, tls_cert, tls_key, mutual=mtls)
        default_listen = DEFAULT_SERVER_LISTEN if tls is None else DEFAULT_SERVER_LISTEN_TLS
        zenoh = validate_model(
            ZenohConfig,
            {
                "mode": "peer",
                "listen": list(listen) or ([] if connect else [default_listen]),
                "connect": list(connect),
                "lease_ms": lease_ms,
                "id": zenoh_id,
                "tls": None if tls is None else tls.model_dump(),
                "allow": list(allow),
            },
            source="openral serve's options",
        )
        # Loaded only here: the Zenoh server imports eclipse-zenoh (the 'remote' extra).
        server_module = importlib.import_module("openral_remote.server")
        keep_message_memory()  # this process moves camera-sized messages: glibc keeps their memory for reuse
        robot, rate = _robot_and_rate(robot_id, scene_path, rate_hz)
        keys = PolicyKeys.of(robot.robot_id, name or skill_id)
        identity = claim_server_id(keys, zenoh.id)
        zenoh = zenoh.model_copy(update={"id": identity.zid})
        with (
            identity,
            command_span(
                "serve",
                scene_path or Path(keys.prefix),
                otlp_endpoint=otlp_endpoint,
                otlp_protocol=otlp_protocol,
                trace_sample_ratio=None,
            ),
        ):
            plugin = SKILL_REGISTRY.resolve(skill_id, field="--skill")
            skill: RSkillBase = plugin.from_config(params, robot=robot, rate_hz=rate)
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
            server: Any = server_module.PolicyServer(
                skill,
                keys=keys,
                zenoh=zenoh,
                meta=meta,
                limits=limits,
                factory=lambda: plugin.from_config(params, robot=robot, rate_hz=rate),  # a robot's own instance
            )
            with server:
                security = "plain" if tls is None else ("mutual TLS" if tls.mutual else "TLS")
                click.echo(
                    f"serving {keys.prefix} ({skill_id}, chunk {meta.chunk_size}, model {meta.model_hash[:12]}, "
                    f"warm-up {server.meta.warmup_ms:.0f} ms) on {', '.join(zenoh.listen or zenoh.connect)}, "
                    f"{security}, Zenoh id {zenoh.id}",
                    err=True,
                )
                stopped.wait()
            stats = server.stats
            click.echo(
                f"served {stats.served} in {stats.batches} inferences (largest batch {stats.largest_batch}), "
                f"superseded {stats.superseded}, refused {stats.refused}, errors {stats.errors}, resets {stats.resets}",
                err=True,
            )
