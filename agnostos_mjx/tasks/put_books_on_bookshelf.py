"""put_books_on_bookshelf (unseen, Level 1): put 1, 2 or 3 books upright on
the bookshelf's top shelf."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, all_of
from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    grasp_site,
    pose_in_root,
    sensor_volume,
    yaw_of,
)
from agnostos_mjx.tasks.builders.household import shelf_unit, solid

WOOD = (0.55, 0.35, 0.2)
BOOK_COLORS = ((0.6, 0.1, 0.1), (0.1, 0.3, 0.6), (0.2, 0.5, 0.2))
BOOK_HALF = (0.025, 0.06, 0.085)  # thickness (x), width (y), height (z)
BOOK_SLOTS_X = (-0.1, 0.0, 0.1)  # each book's x on the table and on the shelf
BOOKS_Y, SHELF_Y = 0.1, -0.15
SHELF_HALF, SHELF_TOP, SIDE_HEIGHT = (0.18, 0.08), 0.182, 0.33
SUCCESS_CENTER, SUCCESS_HALF = (0.0, SHELF_Y, SHELF_TOP + 0.06), (0.16, 0.07, 0.06)
ORDER = (2, 1, 0)  # RLBench stacks book2 first, then book1, then book0
GRIP_BELOW_TOP = 0.03
CARRY_Z = 0.40
# Pre-grasp: the tip 6 cm above the grip point, the finger pads (0.9 cm below the tip)
# 2 cm above the book's top.
PRE_GRASP = 0.06
# Shelf and books in the root frame: x[-0.18, 0.18], y[-0.236, 0.16].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.18, 0.198), (0.0, -0.038)


class PutBooksOnBookshelf(Task):
    name = "put_books_on_bookshelf"
    split = Split.LEVEL1
    num_variations = 3
    objects = {"first book": "book0", "second book": "book1", "third book": "book2",
               "bookshelf": "bookshelf"}
    frames = ("bookshelf_root", "success")
    graspables = ("book0", "book1", "book2")
    grasp_points = ("book0_grip", "book1_grip", "book2_grip")
    graspable_radius = (0.01, 0.01, 0.01)
    notes = (
        "Layout designed (RLBench's scene model is not documented): a two-level bookshelf "
        "behind the root (open top compartment = the 'top shelf'), three books standing upright "
        "in a row in front of it. The expert lifts each book by its top edge (moving between books "
        "high and straight down to a pre-grasp pose just above it, RLBench plans those paths) and lowers it "
        "upright onto the top shelf, book2 first as RLBench's order. Success as RLBench: the "
        "first n books of (book2, book1, book0) inside the top shelf's volume, no NothingGrasped. "
        "Descriptions verbatim, including 'put 1 books on bookshelf'."
    )

    def descriptions(self, variation: int) -> list[str]:
        n = variation + 1
        return [f"put {n} books on bookshelf", f"pick up {n} books and place them on the top shelf",
                f"stack {n} books up on the top shelf"]

    def build(self, scene) -> None:
        root = scene.mocap("bookshelf_root")
        shelf_unit(root, "bookshelf", (0.0, SHELF_Y, 0.0), SHELF_HALF, SHELF_TOP, SIDE_HEIGHT, WOOD)
        sensor_volume(root, "success", SUCCESS_CENTER, SUCCESS_HALF)
        for k, rgb in enumerate(BOOK_COLORS):
            book = free_body(scene, f"book{k}")
            solid(book, BOOK_HALF, (0, 0, 0), rgb, 0.15)
            grasp_site(book, f"book{k}_grip", [0, 0, BOOK_HALF[2] - GRIP_BELOW_TOP])

    def sample(self, key, variation) -> Placement:
        # RLBench turns the root by at most +-90 degrees and samples nothing else.
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi / 2, offset=FOOTPRINT_CENTER)
        bodies = {"bookshelf_root": (pos, quat)}
        for k, x in enumerate(BOOK_SLOTS_X):
            bodies[f"book{k}"] = pose_in_root(pos, quat, (x, BOOKS_Y, BOOK_HALF[2] + 0.001))
        return Placement(bodies=bodies)

    def success(self, variation):
        books = [Detected(f"book{k}", "success", SUCCESS_HALF) for k in ORDER]
        return all_of(books, count=variation + 1)

    def expert(self, obs, variation):
        # Fingers close across the books' thickness (the root's x axis).
        quat = down_grasp(yaw_of(obs.quat("bookshelf_root")) + jnp.pi / 2)
        high = obs.pos("bookshelf_root")[2] + CARRY_Z
        release_tip = SHELF_TOP + 0.003 + 2 * BOOK_HALF[2] - GRIP_BELOW_TOP
        steps, valid = [], []
        for j, k in enumerate(ORDER):
            grip = obs.pos(f"book{k}_grip")
            slot = in_frame(obs, "bookshelf_root", (BOOK_SLOTS_X[k], SHELF_Y, release_tip))
            # The 0.26 m descent from the carrying height turns the folded wrist fast
            # enough that the arm lags the straight line by up to 3 cm and a pad lands
            # on the book; it ends just above the book instead (the lag settles there,
            # RLBench's pre-grasp waypoint) and the last 6 cm go straight down.
            steps += [
                (grip.at[2].set(high), quat, 1.0),  # straight above: clear of shelved books
                (grip.at[2].add(PRE_GRASP), quat, 1.0),  # pre-grasp, just above the book
                (grip, quat, 0.0),
                (grip.at[2].set(high), quat, 0.0),
                (slot.at[2].set(high), quat, 0.0),
                (slot, quat, 1.0),
                (slot.at[2].set(high), quat, 1.0),
            ]
            valid += [j <= variation] * 7
        return key_actions(steps, valid=jnp.stack([jnp.asarray(v) for v in valid]))


TASK = PutBooksOnBookshelf()
