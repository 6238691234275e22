"""Published AGNOSTOS numbers (success %, 3 runs x 25 episodes), for the
optional comparison column of the report (spec: xicm_reference.md §10)."""

from __future__ import annotations

# task -> (X-ICM 7B, X-ICM 72B, pi0, VoxPoser, RVT2)
METHODS = ("X-ICM 7B", "X-ICM 72B", "pi0", "VoxPoser", "RVT2")
_TABLE = {
    "put_toilet_roll_on_stand": (1.3, 6.7, 0.0, 0.0, 0.0),
    "put_knife_on_chopping_board": (26.7, 69.3, 5.3, 0.0, 1.3),
    "close_fridge": (22.7, 12.7, 85.3, 0.0, 0.0),
    "close_microwave": (45.3, 58.7, 24.0, 0.0, 17.3),
    "close_laptop_lid": (33.3, 34.0, 40.0, 5.3, 42.7),
    "phone_on_base": (57.3, 68.0, 1.3, 8.0, 1.3),
    "toilet_seat_down": (48.0, 51.3, 64.0, 28.0, 62.7),
    "lamp_off": (58.7, 86.7, 18.7, 88.7, 2.7),
    "lamp_on": (50.7, 74.7, 8.0, 25.3, 1.3),
    "put_books_on_bookshelf": (1.3, 2.0, 1.3, 0.0, 0.0),
    "put_umbrella_in_umbrella_stand": (0.0, 1.3, 0.0, 0.0, 1.3),
    "open_grill": (8.0, 5.3, 33.3, 0.0, 5.3),
    "put_rubbish_in_bin": (18.7, 18.7, 1.3, 82.7, 34.7),
    "take_usb_out_of_computer": (98.7, 98.7, 97.3, 32.0, 22.7),
    "take_lid_off_saucepan": (20.0, 13.3, 0.0, 76.0, 40.0),
    "take_plate_off_colored_dish_rack": (6.7, 4.7, 1.3, 0.0, 0.0),
    "basketball_in_hoop": (9.3, 36.0, 0.0, 8.0, 0.0),
    "scoop_with_spatula": (0.0, 0.7, 0.0, 0.0, 0.0),
    "straighten_rope": (6.7, 16.0, 0.0, 0.0, 0.0),
    "turn_oven_on": (16.0, 20.7, 14.7, 0.0, 0.0),
    "beat_the_buzz": (2.7, 7.3, 5.3, 1.3, 1.3),
    "water_plants": (5.3, 2.7, 1.3, 0.0, 1.3),
    "unplug_charger": (4.0, 2.7, 0.0, 4.0, 1.3),
}
_GROUPS = {
    "Level-1": (28.6, 37.6, 21.7, 18.1, 13.1),
    "Level-2": (16.9, 20.3, 12.0, 12.1, 6.7),
    "All": (23.5, 30.1, 17.5, 15.6, 10.3),
}


def published(method: str) -> dict[str, float]:
    """Task and group name -> published success % of `method` (one of METHODS)."""
    if method not in METHODS:
        raise KeyError(f"unknown published method {method!r}; choose from {', '.join(METHODS)}")
    k = METHODS.index(method)
    return {name: row[k] for name, row in {**_TABLE, **_GROUPS}.items()}
