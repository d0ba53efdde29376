"""The one colour palette of the ground vehicles: target id ``k`` is painted ``PALETTE[k - 1]``.

Saturated colours chosen to stand apart from each other and from soil, crops and canopies, so
that the colour alone tells the YOLO detector which target it sees (class = target id - 1).
"""

from __future__ import annotations

#: RGB in ``[0, 1]`` per target id 1..8.
PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.90, 0.10, 0.10),  # 1 red
    (0.10, 0.30, 0.95),  # 2 blue
    (0.95, 0.90, 0.10),  # 3 yellow
    (0.90, 0.10, 0.85),  # 4 magenta
    (0.10, 0.90, 0.95),  # 5 cyan
    (1.00, 0.50, 0.00),  # 6 orange
    (0.97, 0.97, 0.97),  # 7 white
    (0.06, 0.06, 0.06),  # 8 black
)
COLOUR_NAMES: tuple[str, ...] = (
    "red", "blue", "yellow", "magenta", "cyan", "orange", "white", "black",
)  # fmt: skip
MAX_TARGETS = len(PALETTE)


def target_colour(target_id: int) -> tuple[float, float, float]:
    """RGB in ``[0, 1]`` of target ``target_id`` (1-based); raises for ids beyond the palette."""
    if not 1 <= target_id <= MAX_TARGETS:
        raise ValueError(
            f"target id {target_id} has no colour: the palette covers 1..{MAX_TARGETS}"
        )
    return PALETTE[target_id - 1]
