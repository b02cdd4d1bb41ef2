"""Console benchmark: what the live web console costs the loop, with a real browser watching.

The shipped 30 Hz twin-camera deployment (``deployments/so101_twin_camera.yaml``: the MuJoCo
twin, its camera rendering 320x240 at up to 30 fps, the hello skill, the envelope) runs
``--seconds`` per run in three variants, alternating round by round in one sitting so drifting
load hits all of them alike:

* ``off``: the deployment as shipped;
* ``console``: with ``--console 127.0.0.1:0`` (the console and the thumbnails it needs), no page open;
* ``console+page``: the same with the page open in headless Chromium (Selenium), which renders
  every state and camera frame the server pushes.

Reported per variant: tick-start jitter p50/p99 (median over the rounds) and the worst round's
p99, tick p99 and missed slots; then the ``console+page`` / ``off`` ratio of the median p99.
Target: at most 1.2x.

Run:  uv run python benchmarks/console_cost.py [--seconds 20] [--rounds 3]
(needs the twin's camera: EGL or OSMesa, and Debian's chromium and chromium-driver)
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

from selenium import webdriver
from selenium.webdriver.chrome.options import Options
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from _common import machine_line
from openral_cli.console import ConsoleAddress, attach_console, consoles_of, with_console
from openral_core import RobotEnvironment, RunResult, StopReason
from openral_runner.factory import build_runner

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENT = ROOT / "deployments" / "so101_twin_camera.yaml"
VARIANTS = ("off", "console", "console+page")


def start_browser() -> Any:
    options = Options()
    options.binary_location = "/usr/bin/chromium"
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"):
        options.add_argument(argument)
    return webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)


def run_once(variant: str, seconds: float, browser: Any) -> tuple[RunResult, int]:
    """One run of ``variant``; returns its result and the camera frames the page showed (0 without a page)."""
    env = RobotEnvironment.from_yaml(DEPLOYMENT)
    if variant != "off":
        env = with_console(env, ConsoleAddress("127.0.0.1", 0))
    runner, skill = build_runner(env, base_dir=DEPLOYMENT.parent)
    skill.configure()
    skill.activate()
    runner.activate()
    shown = 0
    try:
        attach_console(runner, stop=runner.request_stop)
        if variant == "console+page":
            (console,) = consoles_of(runner.observers)
            browser.get(console.url)
            wait = WebDriverWait(browser, 30)
            wait.until(lambda d: d.find_element(By.ID, "connection").text == "live")  # the page's socket is open
        else:
            browser.get("about:blank")
        time.sleep(1.0)  # let the camera and the page settle before measuring
        result = runner.run(duration_s=seconds)
        if variant == "console+page":  # what the page showed: its tick counter, and the camera's image
            shown = int(browser.find_element(By.ID, "ticks").text)
            if not browser.find_elements(By.ID, "camera-front"):
                raise RuntimeError("the page never showed the camera")
    finally:
        runner.deactivate()
        skill.shutdown()
    return result, shown


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    print(machine_line())
    browser = start_browser()
    results: dict[str, list[RunResult]] = {v: [] for v in VARIANTS}
    page_ticks: list[int] = []
    try:
        for round_idx in range(args.rounds):
            for variant in VARIANTS:
                result, shown = run_once(variant, args.seconds, browser)
                results[variant].append(result)
                if shown:
                    page_ticks.append(shown)
                print(
                    f"round {round_idx + 1} {variant:13s} jitter p99 {result.start_jitter_us_p99:8.1f} µs  "
                    f"ticks {result.n_ticks}  stale reads {result.stale_reads}  stopped: {result.stop_reason}",
                    flush=True,
                )
    finally:
        browser.quit()
    print(machine_line())
    print()
    print(f"twin + camera at 30 Hz, {args.rounds} rounds x {args.seconds:g} s per variant (median over rounds)")
    print(
        "| variant | jitter p50 µs | jitter p99 µs | worst round p99 µs | tick p99 ms | missed slots "
        "| stale reads | runs stopped early |"
    )
    print("|---|---|---|---|---|---|---|---|")
    medians = {}
    for variant in VARIANTS:
        runs = results[variant]
        medians[variant] = statistics.median(r.start_jitter_us_p99 for r in runs)
        print(
            f"| {variant} | {statistics.median(r.start_jitter_us_p50 for r in runs):.1f} | {medians[variant]:.1f} | "
            f"{max(r.start_jitter_us_p99 for r in runs):.1f} | {statistics.median(r.tick_ms_p99 for r in runs):.2f} | "
            f"{sum(r.missed_slots for r in runs)} | {sum(r.stale_reads for r in runs)} | "
            f"{sum(r.stop_reason != StopReason.DURATION for r in runs)} |"
        )
    ratio = medians["console+page"] / max(medians["off"], 1e-9)
    print()
    print(f"console+page / off, median jitter p99: {ratio:.2f}x (target <= 1.2x)")
    if page_ticks:
        print(f"the page's tick counter at each run's end: {page_ticks}")


if __name__ == "__main__":
    main()
