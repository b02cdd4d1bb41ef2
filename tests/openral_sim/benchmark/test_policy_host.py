"""A row's policy server: its workers run remote_policy with its parameters, and closing always stops it."""

from __future__ import annotations

from typing import Any

import pytest

from openral_sim.benchmark.policy_host import RowPolicyServer


class FakeHost:
    """A policy host's three calls, recorded."""

    def __init__(self, stats_fail: bool = False) -> None:
        self.stats_fail = stats_fail
        self.closed = False

    def client_params(self) -> dict[str, Any]:
        return {"policy": "evaluated", "zenoh": {"connect": ["tcp/127.0.0.1:7447"]}}

    def stats(self) -> dict[str, int]:
        if self.stats_fail:
            raise RuntimeError("server gone")
        return {"served": 12, "largest_batch": 2}

    def close(self) -> None:
        self.closed = True


class Remote:
    """A Ray actor method: ``.remote()`` gives a reference that ``ray.get`` resolves."""

    def __init__(self, method: Any) -> None:
        self.method = method

    def remote(self) -> tuple[str, Any]:
        return ("ref", self.method)


class FakeActor:
    def __init__(self, host: FakeHost) -> None:
        self.client_params = Remote(host.client_params)
        self.stats = Remote(host.stats)
        self.close = Remote(host.close)


class FakeRay:
    def __init__(self) -> None:
        self.gets = 0

    def get(self, reference: tuple[str, Any]) -> Any:
        self.gets += 1
        return reference[1]()


def test_workers_run_remote_policy_with_the_servers_parameters_and_closing_gives_what_it_served() -> None:
    host = FakeHost()
    server = RowPolicyServer(host)
    assert server.skill_id == "remote_policy"
    assert server.params == host.client_params()
    assert server.close() == {"served": 12, "largest_batch": 2}
    assert host.closed


def test_the_server_is_stopped_even_when_its_statistics_cannot_be_read() -> None:
    host = FakeHost(stats_fail=True)
    server = RowPolicyServer(host)
    with pytest.raises(RuntimeError, match="server gone"):
        server.close()
    assert host.closed


def test_a_ray_actors_methods_are_called_remotely() -> None:
    host, ray = FakeHost(), FakeRay()
    server = RowPolicyServer(FakeActor(host), ray=ray)
    assert server.params["policy"] == "evaluated"
    assert server.close()["served"] == 12
    assert host.closed
    assert ray.gets == 3  # client_params, stats and close: each through ray.get
