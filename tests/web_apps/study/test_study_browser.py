"""A participant's whole visit in a real headless browser (Debian's Chromium driven by Playwright), through the
study pages' own controls: consent, instructions, the practice, two real-time games by key presses (the first
reloaded mid-game), the questions and the forced choice, the completion code; then the database holds exactly that."""

import shutil
import threading
import time

import pytest

pytest.importorskip("fastapi", reason="kitchen-study needs the play extra: pip install .[play]")
playwright = pytest.importorskip("playwright.sync_api", reason="the browser test needs playwright: pip install .[test]")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None:
    pytest.skip("no Chromium on this machine (Debian: apt-get install chromium)", allow_module_level=True)

import uvicorn  # noqa: E402
from tiny_study import TOKEN, study_config  # noqa: E402

from torch_kitchen.records import read_record  # noqa: E402
from web_apps.play.game import ACTIONS  # noqa: E402
from web_apps.study.client import base_url, loopback_listener  # noqa: E402
from web_apps.study.config import FORCED_CHOICE, load_study  # noqa: E402
from web_apps.study.server import create_study_app, open_study  # noqa: E402

# Headless, and no calls home: this machine's network is closed (see the README).
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]
KEYS = ["ArrowLeft", "ArrowUp", "Space", "KeyD", "KeyS", "KeyE"]
TIME_LEFT = "Number((document.getElementById('time').textContent.match(/time left (\\d+)/) || [])[1])"


@pytest.fixture()
def study(tmp_path):
    """A two-condition study in real time with short, fast games, served by uvicorn on a thread."""
    config = load_study(study_config(tmp_path, pace="realtime", tick_ms=40, max_steps=20, practice_steps=12))
    database, token, operator = open_study(config, TOKEN)
    listener = loopback_listener()
    server = uvicorn.Server(uvicorn.Config(create_study_app(config, database, token, operator), log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    yield base_url(listener), config, database
    server.should_exit = True
    thread.join(timeout=10)
    database.close()


def heading(page, text: str) -> None:
    page.wait_for_selector(f"h1:text-is('{text}')", timeout=30_000)


def press_keys_until_over(page) -> None:
    """Presses keys through a game until it is over, then continues with the page's own button."""
    page.wait_for_function(f"{TIME_LEFT} >= 0 || document.getElementById('error').textContent", timeout=60_000)
    assert page.text_content("#error") == ""  # the game's first state drawn, not refused
    while not page.is_visible("#again"):
        for key in KEYS:
            page.keyboard.press(key)
        time.sleep(0.03)
    assert page.text_content("#over").startswith("Game over")
    page.click("#again")


def answer(page, values: dict[str, int]) -> None:
    for item, value in values.items():
        page.check(f'input[name="{item}"][value="{value}"]')
    page.click("#send")


def test_a_participant_goes_through_the_study_in_the_browser_and_a_reload_resumes_the_game(study):
    base, config, database = study
    errors = []
    with playwright.sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        page = browser.new_page()
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(f"{base}/?token={TOKEN}&participant=browser-1")
        heading(page, "Consent")
        assert "/p/" in page.url and f"token={TOKEN}" in page.url  # the participant's own page, the token kept
        page.click("#agree")
        heading(page, "How to play")
        page.click("#start")
        heading(page, "Practice game 1")
        press_keys_until_over(page)

        heading(page, "Game 1 of 2")
        page.wait_for_function(f"{TIME_LEFT} < {config.max_steps - 5}", timeout=60_000)
        page.keyboard.press("ArrowRight")
        page.reload()  # mid-game: the same stage again, its game from the start
        heading(page, "Game 1 of 2")
        press_keys_until_over(page)
        heading(page, "After game 1")
        assert not page.is_visible(f'input[name="{FORCED_CHOICE}"]')  # nothing to choose between yet
        page.click("#send")  # nothing chosen: the page asks for every answer and posts nothing
        assert "answer every question" in page.text_content("#error")
        page.evaluate("done({answers: {helpful: 9}})")  # a crafted post: the server's refusal shows on the page
        page.wait_for_function("document.getElementById('error').textContent.includes('answer exactly')")
        answer(page, {"helpful": 2, "predictable": 5})

        heading(page, "Game 2 of 2")
        press_keys_until_over(page)
        heading(page, "After game 2")
        answer(page, {"helpful": 4, "predictable": 1, FORCED_CHOICE: 0})
        heading(page, "Thank you")
        code = page.text_content("#code")
        browser.close()
    assert errors == []

    (participant,) = database.rows("SELECT * FROM participants")
    assert participant["external_id"] == "browser-1" and participant["finished"] is not None
    assert code == participant["completion_code"]
    stages = [(row["stage"], row["kind"]) for row in database.rows("SELECT * FROM stages ORDER BY stage")]
    assert stages == list(enumerate(["consent", "instructions", "practice", "game", "questions", "game",
                                     "questions"]))
    answers = {(row["stage"], row["item"]): row["value"] for row in database.rows("SELECT * FROM answers")}
    assert answers == {(4, "helpful"): 2, (4, "predictable"): 5, (6, "helpful"): 4, (6, "predictable"): 1,
                       (6, FORCED_CHOICE): 0}
    games = database.rows("SELECT * FROM games ORDER BY stage, attempt")
    assert [(g["stage"], g["attempt"], g["status"], g["reason"]) for g in games] == [
        (2, 0, "finished", "finished"), (3, 0, "cut", "disconnected"), (3, 1, "finished", "finished"),
        (5, 0, "finished", "finished")]
    slots = {(slot.practice, slot.position): slot for slot in database.slots(0)}
    for game in games:
        header, steps, end = read_record(config.folder / game["record"])
        slot = slots[(bool(game["practice"]), game["position"])]
        assert (game["condition"], header["layout_name"], header["seed"]) == (slot.condition, slot.kitchen, slot.seed)
        assert end["reason"] == game["reason"] and len(steps) == game["steps"]
        if game["status"] == "finished":
            assert game["steps"] == (config.practice_steps if game["practice"] else config.max_steps)
            pressed = {step["actions"][config.seat] for step in steps}
            assert pressed - {ACTIONS["stay"]}, game["record"]  # the keys reached the kitchen
