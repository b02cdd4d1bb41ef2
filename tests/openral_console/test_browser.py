"""The console in a real browser (headless Chromium through Selenium) watching and stopping real commands.

``openral record`` on the twin with its camera: the page shows the camera's image changing, the
tick counter rising, "Next episode" commits the episode (the dataset's meta says so), "Stop" ends
the recording (the summary is printed, exit 0). ``openral deploy``: "Stop" ends the run in order
and the RunResult is printed. Every wait is on a condition (WebDriverWait, a stderr line).
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
URL = re.compile(r"console: (http://\S+)")
WAIT_S = 60

webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium (the dev group)")
from selenium.webdriver.chrome.options import Options  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

# A checksum of a camera image's pixels, or null until it has loaded (a blob image: same origin, readable).
PIXELS = """
const img = document.getElementById(arguments[0]);
if (!img || !img.complete || !img.naturalWidth) return null;
const canvas = document.createElement("canvas");
canvas.width = img.naturalWidth; canvas.height = img.naturalHeight;
const g = canvas.getContext("2d");
g.drawImage(img, 0, 0);
const data = g.getImageData(0, 0, canvas.width, canvas.height).data;
let sum = 0;
for (let i = 0; i < data.length; i += 3) sum = (sum * 31 + data[i]) >>> 0;
return sum;
"""


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Headless Chromium (Debian's chromium and chromium-driver); skips naming the script that installs them."""
    for binary in (CHROMIUM, CHROMEDRIVER):
        if shutil.which(binary) is None:
            pytest.skip(f"needs {binary} (Debian chromium and chromium-driver): run scripts/install-system-deps.sh")
    options = Options()
    options.binary_location = CHROMIUM
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--mute-audio"):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def _open_console(browser: Any, proc: Any) -> WebDriverWait:
    url = URL.search(proc.wait_for("console: http://", timeout=WAIT_S))
    assert url is not None
    browser.get(url.group(1))
    wait = WebDriverWait(browser, WAIT_S)
    wait.until(lambda d: d.find_element(By.ID, "connection").text == "live")
    return wait


def _click(browser: Any, wait: WebDriverWait, control: str) -> None:
    button = wait.until(lambda d: _enabled(d, f"control-{control}"))
    button.click()


def _enabled(driver: Any, element_id: str) -> Any:
    found = driver.find_elements(By.ID, element_id)
    return found[0] if found and found[0].is_enabled() else False


def _ticks(driver: Any) -> int:
    return int(driver.find_element(By.ID, "ticks").text)


def _light_camera_deployment(tmp_path: Path) -> Path:
    """The shipped twin-camera deployment with a smaller, slower camera (two CI cores also run a browser)."""
    config = yaml.safe_load((ROOT / "deployments" / "so101_twin_camera.yaml").read_text())
    config["sensors"][0].update({"fps": 15, "width": 160, "height": 120, "max_age_ms": 500})
    config.pop("realtime", None)
    path = tmp_path / "twin_camera.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.mark.gl
@pytest.mark.mujoco
@pytest.mark.slow
def test_record_from_the_browser_camera_ticks_next_episode_and_stop(browser, deploy_process, tmp_path) -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    out = tmp_path / "ds"
    proc = deploy_process(
        ["record", "--config", str(_light_camera_deployment(tmp_path)), "--dataset-out", str(out),
         "--episodes", "2", "--episode-time-s", "120", "--reset-time-s", "0", "--vcodec", "h264",
         "--console", "127.0.0.1:0"],
        through_uv=True,
    )  # fmt: skip
    wait = _open_console(browser, proc)

    first = wait.until(lambda d: d.execute_script(PIXELS, "camera-front"))
    wait.until(lambda d: d.execute_script(PIXELS, "camera-front") not in (None, first))  # the arm moves
    ticks = _ticks(browser)
    wait.until(lambda d: _ticks(d) >= ticks + 10)
    assert browser.find_element(By.ID, "skill").text == "hello"
    assert browser.find_element(By.ID, "episode").text == "0"
    assert browser.find_elements(By.CSS_SELECTOR, "#joints canvas")  # one plot per joint
    labels = [b.text for b in browser.find_elements(By.CSS_SELECTOR, "#controls button")]
    assert labels == ["Next episode", "Re-record", "Stop"]

    _click(browser, wait, "next")
    proc.wait_for("episode 2/2", timeout=WAIT_S)  # printed once episode 1 was committed
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 1
    wait.until(lambda d: d.find_element(By.ID, "episode").text == "1")

    _click(browser, wait, "stop")
    wait.until(lambda d: d.find_element(By.ID, "connection").text == "run ended")
    code, _ = proc.finish(timeout=WAIT_S)
    assert code == 0, proc.stderr
    assert "recorded 2 episode(s)" in proc.stderr
    assert json.loads((out / "meta" / "info.json").read_text())["total_episodes"] == 2


@pytest.mark.mujoco
def test_deploy_stop_button_ends_the_run_in_order_and_prints_the_run_result(browser, deploy_process) -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    hello = ROOT / "deployments" / "so101_twin_hello.yaml"
    proc = deploy_process(["deploy", "--config", str(hello), "--console", "127.0.0.1:0", "--duration", "120"])
    wait = _open_console(browser, proc)
    wait.until(lambda d: _ticks(d) > 10)
    assert [b.text for b in browser.find_elements(By.CSS_SELECTOR, "#controls button")] == ["Stop"]
    assert browser.find_element(By.ID, "task").text == "wave hello"
    _click(browser, wait, "stop")
    wait.until(lambda d: d.find_element(By.ID, "connection").text == "run ended")
    code, stdout = proc.finish(timeout=WAIT_S)
    assert code == 0, proc.stderr
    assert "stopped: stop_requested" in stdout
