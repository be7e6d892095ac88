"""Offscreen rendering: a camera rendered by one thread can be freed by another."""

import threading

import numpy as np

from services.sim.worlds import make_world
from shared.tasks import get_task


def test_a_world_rendered_in_a_worker_thread_closes_cleanly_from_another():
    # A service renders in its workers' threads; the world is freed at exit from the main one.
    task = get_task("box_stacking")
    made = {}

    def work():
        world = make_world(task.name, 32)
        rng = np.random.default_rng(0)
        world.reset(task.sample_state(rng), rng)
        made["image"], made["world"] = world.render(), world

    worker = threading.Thread(target=work)
    worker.start()
    worker.join()
    assert made["image"].shape == (32, 32, 3)
    made["world"].close()  # EGL_BAD_ACCESS before: the dead worker still held the context
