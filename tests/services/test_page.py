"""The plan viewer in a real browser: headless Debian chromium driven by Playwright, against the
real stack (router, services on the shipped models, gateway) on loopback ports.

Every test fails on a console error or an uncaught exception of the page, except the HTTP
error statuses that a test provokes on purpose (Chromium logs those as console errors too).
`LSR_PAGE_SCREENSHOT=docs/images/plan_viewer.png` also saves the README's screenshot.
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import Browser, Page, expect, sync_playwright

from services.stack import Stack, StackConfig, free_port
from shared.tasks import get_task

MODEL = Path(__file__).resolve().parents[2] / "models" / "box_stacking"
CLOTH_MODEL = MODEL.parent / "cloth_folding"
TASK = get_task("box_stacking")
CLOTH = get_task("cloth_folding")
ROPE_MODEL = MODEL.parent / "rope_box"
ROPE = get_task("rope_box")
TIMEOUT_MS = 30_000
# assertions wait as long as actions do: on a loaded machine a reply may take seconds
expect.set_options(timeout=TIMEOUT_MS)


def chromium() -> str:
    """Debian's chromium (`make install` puts it there); never a skip: the tests must run."""
    found = os.environ.get("LSR_CHROMIUM") or shutil.which("chromium")
    if found is None:
        pytest.fail("no chromium on PATH: run `make install` (apt-get install -y chromium)")
    return found


@pytest.fixture(scope="module")
def stack(tmp_path_factory, patient) -> Iterator[Stack]:
    config = StackConfig(
        port=free_port(),
        zenoh_port=free_port(),
        models=(MODEL, CLOTH_MODEL, ROPE_MODEL),
        log_dir=tmp_path_factory.mktemp("page-stack-logs"),
        env=patient,
    )
    with Stack(config) as running:
        running.start()
        running.wait_healthy(90)
        yield running


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
        yield launched
        launched.close()


class Console:
    """Errors the page logs; `expect(status)` allows the resource errors of one HTTP status."""

    def __init__(self, page: Page) -> None:
        self.errors: list[str] = []
        self.allowed: set[int] = set()
        page.on("console", self._console)
        page.on("pageerror", lambda exc: self.errors.append(f"uncaught: {exc}"))

    def _console(self, message) -> None:
        if message.type != "error":
            return
        status = re.search(r"status of (\d{3})", message.text)
        if status and int(status.group(1)) in self.allowed:
            return
        self.errors.append(message.text)

    def expect(self, status: int) -> None:
        self.allowed.add(status)


@pytest.fixture
def page(stack: Stack, browser: Browser) -> Iterator[tuple[Page, Console]]:
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    opened = context.new_page()
    opened.set_default_timeout(TIMEOUT_MS)
    console = Console(opened)
    opened.goto(stack.config.url + "/")
    expect(opened.locator("body")).to_have_attribute("data-ready", "true")
    yield opened, console
    context.close()
    assert console.errors == [], console.errors


def shown_state(page: Page, name: str) -> str:
    return page.locator(f"#{name}-source").inner_text()


def plan_actions(page: Page) -> list[list[dict]]:
    """The actions every shown plan draws, step by step, read from the page."""
    plans = []
    for plan in page.locator(".plan").all():
        steps = plan.locator("figure[data-action]")
        plans.append([json.loads(s.get_attribute("data-action")) for s in steps.all()])
    return plans


def assert_legal(task, start: dict, goal: dict, plans: list[list[dict]]) -> None:
    assert plans
    for actions in plans:
        state = task.parse_state(start)
        for action in actions:
            state = task.apply(state, task.parse_action(action))  # raises on an illegal move
        assert state == task.parse_state(goal)


def test_edit_plan_and_execute_with_the_keyboard_and_the_mouse(page):
    page, _ = page
    assert page.locator("#task option").all_inner_texts() == [
        "box stacking",
        "cloth folding",
        "rope box",
    ]
    # Start (one box a column, yellow on red): yellow onto blue, by keyboard.
    assert shown_state(page, "start") == "[RY] [G] [B]"
    page.focus("#start-col-0")
    page.keyboard.press("Enter")
    page.focus("#start-col-2")
    page.keyboard.press("Enter")
    expect(page.locator("#start-source")).to_have_text("[R] [G] [BY]")
    # Goal (a tower red-green-blue in the middle): a full column takes no box.
    assert shown_state(page, "goal") == "[] [RGB] [Y]"
    page.click("#goal-col-2")
    page.click("#goal-col-1")
    expect(page.locator("#goal-col-2")).to_have_class(re.compile("holding"))
    page.keyboard.press("Escape")
    page.click("#goal-col-1")
    page.click("#goal-col-0")
    expect(page.locator("#goal-source")).to_have_text("[B] [RG] [Y]")
    start, goal = (
        {"stacks": [["red"], ["green"], ["blue", "yellow"]]},
        {"stacks": [["blue"], ["red", "green"], ["yellow"]]},
    )
    expect(page.locator("#start-image")).to_have_attribute("src", re.compile("^data:image/png"))

    page.click("#plan-btn")
    expect(page.locator(".plan").first).to_be_visible()
    assert_legal(TASK, start, goal, plan_actions(page))
    first = page.locator(".plan").first
    steps = first.locator("figure[data-action]").count()
    assert first.locator("svg.marks circle.pick").count() == steps  # every action is drawn
    assert first.locator("figure").count() == steps + 1  # images from start to goal
    expect(first.locator("figcaption").first).to_contain_text("node ")
    expect(first.locator("figcaption").first).to_contain_text("[R] [G] [BY]")  # node's state
    expect(page.locator("#timing")).to_contain_text("gateway")
    expect(page.locator("#roadmap-svg .edge.on")).to_have_count(steps)  # the path, highlighted

    page.locator("#roadmap-svg .node.on, #roadmap-svg .node.end").first.hover()
    tip = page.locator("#node-tip img")
    expect(tip).to_have_attribute("src", re.compile("^blob:"))
    assert page.evaluate("document.querySelector('#node-tip img').naturalWidth") == 64

    page.click("#execute-btn")
    expect(page.locator("#exec-status")).to_have_class("success", timeout=60_000)
    expect(page.locator("#exec-status")).to_contain_text("reached the goal")
    executed = [
        json.loads(s.get_attribute("data-action"))
        for s in page.locator("#exec-steps figure[data-action]").all()
    ]
    assert_legal(TASK, start, goal, [executed])
    if os.environ.get("LSR_PAGE_SCREENSHOT"):
        page.set_viewport_size({"width": 1366, "height": 900})
        page.screenshot(path=os.environ["LSR_PAGE_SCREENSHOT"], full_page=True)


def png_b64_to_file(text: str, path: Path, size: int | None = None) -> Path:
    image = Image.open(io.BytesIO(base64.b64decode(text)))
    if size is not None:
        image = image.resize((size, size))
    image.save(path, format="PNG")
    return path


def test_an_uploaded_image_as_the_start(page, stack, tmp_path):
    page, _ = page
    start = {"stacks": [["red", "yellow"], ["green"], ["blue"]]}  # what the editor shows first
    rendered = httpx.post(
        stack.config.url + "/render",
        json={"task": "box_stacking", "state": start, "seed": 7},
        timeout=30,
    ).json()["image"]
    page.set_input_files("#start-upload", str(png_b64_to_file(rendered, tmp_path / "cam.png")))
    expect(page.locator("#start-source")).to_have_text("uploaded image")
    page.click("#plan-btn")
    expect(page.locator(".plan").first).to_be_visible()
    assert_legal(TASK, start, {"stacks": [[], ["red", "green", "blue"], ["yellow"]]},
                 plan_actions(page))  # fmt: skip


def test_an_image_the_model_does_not_know_is_refused_on_the_page(page, tmp_path):
    page, _ = page
    noise = np.random.default_rng(5).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    Image.fromarray(noise).save(tmp_path / "noise.png")
    page.set_input_files("#start-upload", str(tmp_path / "noise.png"))
    page.click("#plan-btn")
    expect(page.locator("#reason")).to_contain_text("the start image is unlike")
    expect(page.locator("#match .unknown")).to_contain_text("Start: NOT known")
    expect(page.locator("#match .known")).to_contain_text("Goal: known")
    assert page.locator(".plan").count() == 0


def test_an_api_error_is_shown_next_to_its_field(page, tmp_path):
    page, console = page
    console.expect(422)
    small = Image.new("RGB", (8, 8), "white")  # a camera frame is 16 px a side at least
    small.save(tmp_path / "small.png")
    page.set_input_files("#goal-upload", str(tmp_path / "small.png"))
    page.click("#plan-btn")
    error = page.locator("#goal-error")
    expect(error).to_contain_text("Goal image")
    expect(error).to_contain_text("16 to 4096 pixels")
    expect(page.locator("#start-error")).to_be_empty()
    assert page.locator(".plan").count() == 0


def test_a_render_that_comes_late_leaves_an_uploaded_end_and_its_error_alone(page, tmp_path):
    """A state's render still on its way when an image replaces the end (slow under load)."""
    page, console = page
    console.expect(422)
    held: list = []
    page.route("**/render", lambda route: held.append(route))
    page.click("#goal-random")  # the new state's render, held
    for _ in range(200):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the goal's render was not asked for"
    Image.new("RGB", (8, 8), "white").save(tmp_path / "small.png")
    uploaded = base64.b64encode((tmp_path / "small.png").read_bytes()).decode()
    page.set_input_files("#goal-upload", str(tmp_path / "small.png"))
    page.click("#plan-btn")
    expect(page.locator("#goal-error")).to_contain_text("16 to 4096 pixels")
    for route in held:
        route.continue_()
    page.unroute("**/render")
    page.wait_for_load_state("networkidle")
    expect(page.locator("#goal-error")).to_contain_text("16 to 4096 pixels")
    expect(page.locator("#goal-source")).to_have_text("uploaded image")
    assert page.locator("#goal-image").get_attribute("src").endswith(uploaded)


def test_cloth_folds_from_checkboxes(page):
    page, _ = page
    page.select_option("#task", "cloth_folding")
    expect(page.locator("#goal-fold-top_left")).to_be_checked()  # the default goal
    page.check("#start-fold-bottom_right")
    expect(page.locator("#start-source")).to_have_text("bottom_right")
    page.click("#plan-btn")
    expect(page.locator(".plan").first).to_be_visible()
    start, goal = {"folds": ["bottom_right"]}, {"folds": ["top_left"]}
    assert_legal(CLOTH, start, goal, plan_actions(page))
    assert page.locator(".plan svg.marks circle.release").count() >= 2


def test_rope_box_from_the_grid_and_the_rope_menu(page):
    page, console = page
    page.select_option("#task", "rope_box")
    page.click("#start-cell-1-0")  # the green box, picked up
    page.click("#start-cell-1-2")  # and put to the orange box's right
    expect(page.locator("#start-source")).to_have_text("green (1,2) · orange (1,1) · rope straight")
    # The default goal's rope bends round pillar (0, 0) on its left; its right is no state.
    console.expect(422)
    wrong = {"pillar": {"row": 0, "col": 0}, "turn": "right"}
    page.select_option("#goal-rope", json.dumps(wrong, separators=(",", ":")))
    expect(page.locator("#goal-error")).to_contain_text("only bend round pillar (0, 0)")
    page.select_option("#goal-rope", "")  # straight
    expect(page.locator("#goal-source")).to_contain_text("rope straight")
    page.click("#plan-btn")
    expect(page.locator(".plan").first).to_be_visible()
    start = {"boxes": {"green": {"row": 1, "col": 2}, "orange": {"row": 1, "col": 1}}, "rope": None}
    goal = {"boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 0, "col": 1}}, "rope": None}
    assert_legal(ROPE, start, goal, plan_actions(page))


def test_a_stopped_service_shows_as_down_within_seconds(page, stack):
    page, console = page
    console.expect(503)  # /health while the APN is down
    apn = page.locator('#health-services li[data-service="apn"]')
    expect(apn).not_to_have_class("down")
    stack.stop("apn")
    started = time.monotonic()
    expect(apn).to_have_class("down", timeout=10_000)
    assert time.monotonic() - started < 6.0
    expect(page.locator("#health-status")).to_contain_text("apn")
    stack.start_service("apn")
    expect(apn).not_to_have_class("down", timeout=60_000)


def test_the_roadmap_is_drawn_again_once_no_planner_serves_the_version_drawn(page):
    page, _ = page
    expect(page.locator("#roadmap-info")).to_contain_text("roadmap v1")
    asked = []  # while the planners serve the version drawn, it is not asked for again
    page.on("request", lambda r: asked.append(r.url) if r.url.endswith("/roadmap") else None)
    page.wait_for_timeout(4500)  # two health polls
    assert asked == []

    def grown(route):  # the planners now say they plan with v2
        body = route.fetch().json()
        for instance in body["services"]["planner"]["instances"]:
            instance["roadmap_version"] = "v2"
        route.fulfill(json=body)

    with page.expect_request(lambda r: r.url.endswith("/tasks/box_stacking/roadmap")):
        page.route("**/health", grown)
    expect(page.locator("#health-services [data-service=planner]")).to_contain_text("roadmap v2")
