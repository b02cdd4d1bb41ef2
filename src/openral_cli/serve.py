"""``openral serve``: run a policy on this machine (the one with the GPU) for robots elsewhere.

``--protocol`` picks the link: openral's own over Zenoh (the default), openpi's websocket (for
openpi clients: :mod:`openral_remote.openpi_server`) or vla-eval's (its evaluation harness).
Every protocol serves through the same admission, fair queue and batching
(:mod:`openral_remote.service`).

The server's Zenoh id is stable (kept per host and key, :mod:`openral_remote.identity`, unless
``--zenoh-id`` gives one), so robots, which pin the server they first reached, take it back after a
restart, while a second server of the key on this host gets another id and so is seen, and refused.
``--tls-*`` put every link behind TLS (``--mtls``: robots need a certificate too; ``--allow``: only
these certificate names are heard); the files are checked before the policy is loaded.
"""

from __future__ import annotations

import ipaddress
import re
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from openral_cli.command_lifecycle import command_span
from openral_cli.errors import exit_codes
from openral_cli.options import json_object
from openral_cli.serve_limits import limit_options, serve_limits
from openral_cli.signals import StopSignals
from openral_core import RobotManifest, ROSConfigError, SimEnvironment
from openral_core.config import validate_model
from openral_core.config_files import read_config_file
from openral_hal.manifests import load_robot_manifest
from openral_observability.setup import PROTOCOLS
from openral_remote.admission import ServeLimits
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
from openral_remote.meta import PolicyMeta, describe, model_hash
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
        from openral_sim.env import make_env  # noqa: PLC0415 - the simulators: the 'sim' extras

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
    from openral_remote.tls import check_tls  # noqa: PLC0415 - cryptography: the 'remote' extra

    check_tls(tls, prefix="--tls-")
    return tls


PROTOCOLS_SERVED = ("zenoh", "openpi", "vla-eval")
OPENPI_PROFILES = ("openral", "libero", "aloha", "droid")
VLA_EVAL_PROFILES = ("libero", "libero_lerobot", "plain")
DEFAULT_WEBSOCKET_LISTEN = "127.0.0.1:8000"
MAX_API_KEY_BYTES = 4096


def _host_port(listen: tuple[str, ...], protocol: str) -> tuple[str, int]:
    """``--listen HOST:PORT`` of a websocket protocol (one; loopback port 8000 by default).

    Raises:
        ROSConfigError: More than one, or not ``HOST:PORT`` with a port in 0..65535.
    """
    if len(listen) > 1:
        raise ROSConfigError(f"--protocol {protocol} listens on one HOST:PORT", field="--listen")
    text = listen[0] if listen else DEFAULT_WEBSOCKET_LISTEN
    host, colon, port = text.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")
    if not colon or not host or not port.isdecimal() or not 0 <= int(port) <= 65535:
        raise ROSConfigError(
            f"--listen {text!r} is not HOST:PORT", field="--listen", hint="e.g. 127.0.0.1:8000 or 0.0.0.0:8000"
        )
    return host, int(port)


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _api_key(path: Path | None) -> str | None:
    """The key in ``--api-key-file`` (its first line, stripped), or ``None``.

    Raises:
        ROSConfigError: The file is missing, too large, not text, or empty.
    """
    if path is None:
        return None
    text = read_config_file(path, field="--api-key-file", max_bytes=MAX_API_KEY_BYTES)
    key = text.strip().splitlines()[0].strip() if text.strip() else ""
    if not key or not key.isprintable():
        raise ROSConfigError(
            f"{path} holds no API key", field="--api-key-file", hint="write the key on the file's first line"
        )
    return key


def _websocket_server(
    protocol: str,
    skill: RSkillBase,
    *,
    meta: PolicyMeta,
    host: str,
    port: int,
    limits: ServeLimits,
    factory: Callable[[], RSkillBase],
    api_key: str | None,
    tls: TlsConfig | None,
    openpi_profile: str,
    state_names: list[str],
    vla_eval_profile: str = "libero",
) -> Any:
    """The server of a websocket ``protocol`` (a context manager with ``url``, ``meta`` and ``stats``)."""
    if protocol == "openpi":
        from openral_remote.openpi_profiles import PROFILES, OpenpiProfile  # noqa: PLC0415 - the 'remote' extra
        from openral_remote.openpi_server import OpenpiServer  # noqa: PLC0415

        name = PROFILES[PROFILES.index(openpi_profile)]  # click's choice, as the profile's literal type
        profile = OpenpiProfile(name, image_size=None, state_names=state_names if openpi_profile == "openral" else None)
        return OpenpiServer(
            skill,
            meta=meta,
            profile=profile,
            host=host,
            port=port,
            limits=limits,
            factory=factory,
            api_key=api_key,
            tls=tls,
        )
    from openral_remote.vla_eval_server import serve_vla_eval  # noqa: PLC0415 - the 'remote' extra

    return serve_vla_eval(
        skill,
        meta=meta,
        host=host,
        port=port,
        limits=limits,
        factory=factory,
        api_key=api_key,
        tls=tls,
        profile=vla_eval_profile,
    )


@click.command()
@click.option("--skill", "skill_id", required=True, help="The policy to serve (an openral.skills id).")
@click.option(
    "--protocol",
    type=click.Choice(PROTOCOLS_SERVED),
    default="zenoh",
    show_default=True,
    help="openral's Zenoh link, openpi's websocket (openpi clients) or vla-eval's (its evaluation harness).",
)
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
    help=f"Zenoh endpoint to listen on (repeatable; default {DEFAULT_SERVER_LISTEN}); for openpi and vla-eval "
    f"one HOST:PORT (default {DEFAULT_WEBSOCKET_LISTEN}).",
)
@click.option(
    "--openpi-profile",
    type=click.Choice(OPENPI_PROFILES),
    default=None,
    help="--protocol openpi: whose observation dict the clients send: openral's own fields (the default) or "
    "openpi's LIBERO, ALOHA or DROID example's.",
)
@click.option(
    "--vla-eval-profile",
    type=click.Choice(VLA_EVAL_PROFILES),
    default=None,
    help="--protocol vla-eval: how the benchmark's observations map onto openral's: LIBERO's for openral's libero "
    "scenes (the default; libero_lerobot: frames mirrored as in LeRobot's datasets), or names as sent (plain).",
)
@click.option(
    "--api-key-file",
    type=click.Path(path_type=Path),
    default=None,
    help="openpi/vla-eval: clients must send this file's key (Authorization: Api-Key KEY).",
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
    protocol: str,
    skill_params: str | None,
    robot_id: str | None,
    scene_path: Path | None,
    rate_hz: float | None,
    name: str | None,
    listen: tuple[str, ...],
    openpi_profile: str | None,
    vla_eval_profile: str | None,
    api_key_file: Path | None,
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

    With --protocol openpi (or vla-eval) it is served on a websocket at --listen HOST:PORT
    instead (loopback by default; --api-key-file and --tls-* secure it).

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
        if vla_eval_profile is not None and protocol != "vla-eval":
            raise ROSConfigError("--vla-eval-profile is for --protocol vla-eval", field="--vla-eval-profile")
        if protocol != "zenoh":
            zenoh_only = {"--connect": connect, "--zenoh-id": zenoh_id, "--allow": allow}
            for option, value in zenoh_only.items():
                if value:
                    raise ROSConfigError(f"{option} is for --protocol zenoh", field=option)
            if openpi_profile is not None and protocol != "openpi":
                raise ROSConfigError("--openpi-profile is for --protocol openpi", field="--openpi-profile")
            _serve_websocket(
                protocol,
                signals,
                skill_id=skill_id,
                params=params,
                name=name,
                robot_id=robot_id,
                scene_path=scene_path,
                rate_hz=rate_hz,
                listen=listen,
                limits=limits,
                tls=tls,
                api_key_file=api_key_file,
                openpi_profile=openpi_profile,
                vla_eval_profile=vla_eval_profile,
                otlp_endpoint=otlp_endpoint,
                otlp_protocol=otlp_protocol,
            )
            return
        if api_key_file is not None or openpi_profile is not None:
            option = "--api-key-file" if api_key_file is not None else "--openpi-profile"
            raise ROSConfigError(
                f"{option} is for the websocket protocols",
                field=option,
                hint="--protocol openpi or vla-eval; Zenoh links are authenticated with --tls-* --mtls",
            )
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
        from openral_remote.server import PolicyServer  # noqa: PLC0415 - eclipse-zenoh: the 'remote' extra

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
            server = PolicyServer(
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
            _print_stats(server.stats)


def _serve_websocket(
    protocol: str,
    signals: StopSignals,
    *,
    skill_id: str,
    params: dict[str, Any],
    name: str | None,
    robot_id: str | None,
    scene_path: Path | None,
    rate_hz: float | None,
    listen: tuple[str, ...],
    limits: ServeLimits,
    tls: TlsConfig | None,
    api_key_file: Path | None,
    openpi_profile: str | None,
    vla_eval_profile: str | None,
    otlp_endpoint: str | None,
    otlp_protocol: str | None,
) -> None:
    """Serve over a websocket protocol (openpi's or vla-eval's) until stopped."""
    host, port = _host_port(listen, protocol)
    api_key = _api_key(api_key_file)
    keep_message_memory()  # camera-sized messages: glibc keeps their memory for reuse
    if not _is_loopback(host) and api_key is None and tls is None:
        click.echo(
            f"warning: serving on {host}:{port} without --api-key-file or --tls-*: anyone who can reach the "
            "port can run the policy and read its metadata, and the traffic is in clear",
            err=True,
        )
    with command_span(
        "serve",
        scene_path or Path(f"{protocol}/{name or skill_id}"),
        otlp_endpoint=otlp_endpoint,
        otlp_protocol=otlp_protocol,
        trace_sample_ratio=None,
    ):
        robot, rate = _robot_and_rate(robot_id, scene_path, rate_hz)
        plugin = SKILL_REGISTRY.resolve(skill_id, field="--skill")
        skill: RSkillBase = plugin.from_config(params, robot=robot, rate_hz=rate)
        meta = describe(
            skill,
            policy=name or skill_id,
            robot=robot.robot_id,
            action_names=robot.joint_names,
            rate_hz=rate,
            model_hash=model_hash(skill_id, params, Path.cwd()),
        )
        stopped = threading.Event()
        signals.on_stop(lambda _reason: stopped.set())
        server: Any = _websocket_server(
            protocol,
            skill,
            meta=meta,
            host=host,
            port=port,
            limits=limits,
            factory=lambda: plugin.from_config(params, robot=robot, rate_hz=rate),
            api_key=api_key,
            tls=tls,
            openpi_profile=openpi_profile or "openral",
            vla_eval_profile=vla_eval_profile or "libero",
            state_names=list(robot.joint_names),
        )
        with server:
            click.echo(
                f"serving {skill_id} to {protocol} clients on {server.url} (chunk {meta.chunk_size}, "
                f"model {meta.model_hash[:12]}, warm-up {server.meta.warmup_ms:.0f} ms, "
                f"{'API key' if api_key else 'no API key'}, {'TLS' if tls else 'no TLS'})",
                err=True,
            )
            stopped.wait()
        _print_stats(server.stats)


def _print_stats(stats: Any) -> None:
    click.echo(
        f"served {stats.served} in {stats.batches} inferences (largest batch {stats.largest_batch}), "
        f"superseded {stats.superseded}, refused {stats.refused}, errors {stats.errors}, resets {stats.resets}",
        err=True,
    )
