"""End to end in a real headless browser: Debian's Chromium driven by Playwright's Python API."""

import shutil
import socket
import threading
import time

import pytest

pytest.importorskip("fastapi", reason="kitchen-play needs the play extra: pip install .[play]")
playwright = pytest.importorskip("playwright.sync_api", reason="the browser test needs playwright: pip install .[test]")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None:
    pytest.skip("no Chromium on this machine (Debian: apt-get install chromium)", allow_module_level=True)

import torch  # noqa: E402
import uvicorn  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from torch_kitchen.keys import OBSERVATION  # noqa: E402
from torch_kitchen.records import read_record  # noqa: E402
from trainers.humans.behaviour_cloning import HUMAN_ACTION, ProxySettings, fit_proxy, save_proxy  # noqa: E402
from web_apps.play.game import replay  # noqa: E402
from web_apps.play.server import create_app  # noqa: E402

PROXY_KITCHEN = "cramped_room_in_7x7"  # a classic layout drawn inside a 7x7 kitchen, where human proxies play

# Headless, and no calls home: this machine's network is closed (see the README).
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture()
def server(tmp_path):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    # A human proxy in the lobby: fitted (briefly, to made-up games) and saved as `kitchen-humans train` does.
    games = TensorDict({OBSERVATION: torch.randint(0, 2, (32, 2, 7, 7, 26), dtype=torch.uint8),
                        HUMAN_ACTION: torch.randint(0, 6, (32, 2))}, batch_size=[32])
    proxy, _ = fit_proxy(games, ProxySettings(hidden=8, epochs=1))
    save_proxy(proxy, ProxySettings(hidden=8), PROXY_KITCHEN, tmp_path / "runs" / f"human_proxy_{PROXY_KITCHEN}/seed0")
    # A study's server: the page must carry the participants' token on to every request and the game's socket.
    app = create_app(records=tmp_path / "games", tick_ms=60, max_steps=400, runs_root=str(tmp_path / "runs"),
                     token="participant-7")
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}/?token=participant-7", tmp_path / "games"
    server.should_exit = True
    thread.join(timeout=10)


def test_a_person_plays_with_a_human_proxy_and_the_record_replays(server, tmp_path):
    url, records = server
    with playwright.sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        page = browser.new_page()
        page.goto(url)
        assert page.is_visible("text=Arrows or WASD move")  # the controls, before a game starts
        proxy = str(tmp_path / "runs" / f"human_proxy_{PROXY_KITCHEN}" / "seed0")
        page.select_option("#partner", proxy)
        page.select_option("#kitchen", PROXY_KITCHEN)
        page.screenshot(path=str(tmp_path / "lobby.png"))
        page.dblclick("#start")  # one game, however eager the click (the record below is the only one)
        page.wait_for_function("/time left \\d+/.test(document.getElementById('time').textContent)", timeout=60_000)
        first = page.evaluate("document.getElementById('canvas').toDataURL()")
        for key in ["ArrowLeft", "ArrowUp", "Space", "KeyD", "KeyS", "KeyE"] * 3:
            page.keyboard.press(key)
            time.sleep(0.08)
        page.wait_for_function("Number(document.getElementById('time').textContent.split(' ').pop()) < 380")
        assert page.evaluate("document.getElementById('canvas').toDataURL()") != first
        assert page.text_content("#score").startswith("score ")
        assert "you hold" in page.text_content("#holding")
        page.evaluate("socket.send('not an action')")  # the server's refusal shows on the page
        page.wait_for_function("document.getElementById('game-error').textContent.includes('expected')")
        page.screenshot(path=str(tmp_path / "game.png"))
        browser.close()  # the tab closes mid-game: the server ends the game and completes its record
    (record,) = records.glob("*.jsonl")
    for _ in range(100):
        header, steps, end = read_record(record)
        if end is not None:
            break
        time.sleep(0.05)
    assert end is not None and end["reason"] == "disconnected" and len(steps) >= 20
    assert header["partner"] == f"human_proxy_{PROXY_KITCHEN}/seed0" and header["layout_name"] == PROXY_KITCHEN
    assert header["checkpoint"].startswith(proxy)
    pressed = [step["actions"][0] for step in steps]
    assert {0, 1, 3, 5} & set(pressed)  # the person's keys reached the kitchen (up, down, left, interact)
    assert replay(record)["steps"] == len(steps)

