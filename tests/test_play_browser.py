"""``ocv2 play`` end to end: the real command, a real headless Chromium, real key presses, the archive.

One session: a complete episode, one cut short by leaving the page, one cut short by SIGTERM.

Needs Debian's ``chromium`` and ``chromium-driver`` and ``selenium`` (the ``test`` extra). Where no
browser is found the test is skipped with the reason shown in pytest's summary, so the README's test
command passes on a fresh machine; with ``OCV2_REQUIRE_BROWSER=1`` (``.ci/run`` sets it and installs
Chromium) a missing browser is a failure instead. ``OCV2_SAVE_SCREENSHOT=1`` also writes the screenshot it takes to
``docs/img/play.png`` (the picture in docs/play.md).
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cluster.archive import ArchiveReader

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=820,960",
)
FPS, STEPS = 8, 24
UP, DOWN, LEFT, INTERACT, STAY = 3, 1, 2, 5, 4


BROWSER_PACKAGES = "apt-get install -y chromium chromium-driver"


def _browser_paths(environ=os.environ, which=shutil.which) -> tuple[str, str]:
    """Chromium and chromedriver; skipped (visibly) without them, failed if OCV2_REQUIRE_BROWSER=1."""
    chromium = which("chromium") or which("chromium-browser")
    driver = which("chromedriver")
    if chromium and driver:
        return chromium, driver
    missing = " and ".join(name for name, path in (("chromium", chromium), ("chromedriver", driver)) if not path)
    if environ.get("OCV2_REQUIRE_BROWSER") == "1":
        pytest.fail(f"OCV2_REQUIRE_BROWSER=1 but {missing} not found: {BROWSER_PACKAGES}")
    pytest.skip(f"no browser: {missing} not found ({BROWSER_PACKAGES} to run this test)")


@pytest.mark.parametrize(
    "found, require, outcome",
    [
        ({"chromium", "chromedriver"}, "1", None),
        ({"chromium-browser", "chromedriver"}, "", None),
        ({"chromium"}, "", pytest.skip.Exception),
        (set(), "0", pytest.skip.Exception),
        ({"chromium"}, "1", pytest.fail.Exception),
        (set(), "1", pytest.fail.Exception),
    ],
)
def test_missing_browser_skips_unless_required(found, require, outcome):
    def which(name):
        return f"/usr/bin/{name}" if name in found else None

    environ = {"OCV2_REQUIRE_BROWSER": require}
    if outcome is None:
        assert _browser_paths(environ, which)[1] == "/usr/bin/chromedriver"
        return
    with pytest.raises(outcome) as info:
        _browser_paths(environ, which)
    assert "chromedriver" in str(info.value) and "apt-get install" in str(info.value)


def _start_play(out: Path) -> tuple[subprocess.Popen, str, list[str]]:
    """``ocv2 play`` as a user runs it; returns the process, the URL it printed and its output so far."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from cluster.cli import main; sys.exit(main(sys.argv[1:]))",
            "play",
            "grounded_coord_simple",
            "--agent-view-size",
            "2",
            "--max-steps",
            str(STEPS),
            "--fps",
            str(FPS),
            "--port",
            "0",
            "--seed",
            "0",
            "--disconnect-timeout",
            "30",
            "--tile-size",
            "40",
            "--out",
            str(out),
            "--meta",
            "participant=e2e",
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in process.stdout], daemon=True).start()
    seen: list[str] = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=1)
        except queue.Empty:
            assert process.poll() is None, "ocv2 play exited early:\n" + "".join(seen)
            continue
        seen.append(line)
        match = re.search(r"open (http://\S+)", line)
        if match:
            threading.Thread(target=lambda: [seen.append(line) for line in iter(lines.get, None)], daemon=True).start()
            return process, match.group(1), seen
    process.kill()
    pytest.fail("ocv2 play printed no URL within 120 s:\n" + "".join(seen))


def _wait(condition, what: str, timeout: float = 30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    pytest.fail(f"timed out waiting for {what}")


def test_play_in_a_real_browser(tmp_path):
    chromium, driver_path = _browser_paths()
    os.environ.setdefault("SE_OFFLINE", "true")  # Selenium Manager must not try to download anything
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    archive = tmp_path / "human.mcap"
    process, url, output = _start_play(archive)
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in CHROMIUM_FLAGS + (f"--user-data-dir={tmp_path / 'chromium-profile'}",):
        options.add_argument(flag)
    browser = webdriver.Chrome(options=options, service=Service(driver_path))
    try:
        assert "?key=" in url
        browser.get(url.split("?")[0])  # the address without its per-launch key: refused
        assert "open the whole address" in browser.page_source
        browser.get(url)
        status = lambda: browser.find_element(By.ID, "status").text
        phase = lambda: browser.find_element(By.TAG_NAME, "body").get_attribute("data-phase")
        step = lambda: int(browser.find_element(By.TAG_NAME, "body").get_attribute("data-step") or 0)
        frame = lambda: browser.find_element(By.ID, "frame").get_attribute("src")
        _wait(lambda: "Press space" in status(), "the page to join")
        first_frame = frame()
        assert first_frame.startswith("data:image/png;base64,") and "red cook (seat 0)" in browser.page_source
        keys = lambda: browser.find_element(By.TAG_NAME, "body")  # found again after the page reloads

        keys().send_keys(Keys.SPACE)  # start
        _wait(lambda: phase() == "playing", "the episode to start")
        for key in (Keys.ARROW_UP, Keys.ARROW_LEFT, Keys.SPACE, Keys.ARROW_DOWN, Keys.ARROW_RIGHT):
            keys().send_keys(key)
            time.sleep(2 / FPS)  # one key per tick
        _wait(lambda: step() >= 6, "the game to advance")
        assert frame() != first_frame
        assert browser.execute_script("return window.ocv2.sent") == 5
        browser.save_screenshot(str(tmp_path / "play.png"))
        if os.environ.get("OCV2_SAVE_SCREENSHOT") == "1":
            shutil.copy(tmp_path / "play.png", ROOT / "docs" / "img" / "play.png")

        _wait(lambda: phase() == "over", "the episode to end", timeout=STEPS / FPS + 30)
        assert "Episode over" in status()
        keys().send_keys(Keys.SPACE)  # play again ...
        _wait(lambda: phase() == "playing", "the second episode to start")
        keys().send_keys(Keys.ARROW_RIGHT)
        _wait(lambda: step() >= 2, "the second episode to advance")
        browser.get("about:blank")  # ... and close the page mid-episode
        browser.get(url)  # come back: the seat is free again
        _wait(lambda: "cut short (left)" in status(), "the page to rejoin")
        keys().send_keys(Keys.SPACE)
        _wait(lambda: phase() == "playing", "the third episode to start")
        _wait(lambda: step() >= 2, "the third episode to advance")
        process.send_signal(signal.SIGTERM)  # stop the server mid-episode (as Ctrl-C does)
        assert process.wait(timeout=60) == 0, "".join(output)
    finally:
        browser.quit()
        if process.poll() is None:
            process.kill()
    assert "recorded 3 episode(s)" in "".join(output) and "Traceback" not in "".join(output)
    assert (tmp_path / "play.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    complete, cut, stopped = ArchiveReader(archive).iter_episodes()
    assert complete.meta["steps"] == STEPS and not complete.meta["cut_short"] and complete.dones[-1]
    assert complete.meta["human_seats"] == [0] and complete.meta["policies"] == ["human", "stay"]
    assert complete.meta["participant"] == "e2e" and complete.meta["env_params"]["agent_view_size"] == 2
    human = complete.actions[:, 0].tolist()
    assert [a for a in human if a != STAY][:4] == [UP, LEFT, INTERACT, DOWN]  # what was pressed, in order
    moved = (
        np.abs(np.diff(complete.states.agents.x[:, 0])).sum() + np.abs(np.diff(complete.states.agents.dir[:, 0])).sum()
    )
    assert moved > 0  # the human's cook turned or walked
    assert cut.meta["cut_short"] and cut.meta["end_reason"] == "left" and 1 <= cut.meta["steps"] < STEPS
    assert stopped.meta["end_reason"] == "server stopped" and 1 <= stopped.meta["steps"] < STEPS
