"""The particle fields a chunk may carry: name -> unit, components and meaning.

One table for both sides of the wire: the simulation says what it can send (sim.publish),
the render server labels a view's colorbar with the field's unit. A view colours a vector
field ([n, k], k > 1) by its magnitude, so the colorbar of `displacement` reads
"displacement magnitude (m)".
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FieldInfo:
    """A particle field: [n] (components 1) or [n, components] values of `dtype` in `unit`."""

    components: int
    dtype: str  # wire dtype (numpy str)
    unit: str  # SI unit; "1" for a dimensionless number
    description: str


FIELDS: dict[str, FieldInfo] = {
    "displacement": FieldInfo(3, "<f4", "m", "x - x0, from the initial position"),
    "displacement_magnitude": FieldInfo(1, "<f4", "m", "|x - x0|"),
    "velocity": FieldInfo(3, "<f4", "m/s", "particle velocity"),
    "velocity_magnitude": FieldInfo(1, "<f4", "m/s", "|v|"),
    "pressure": FieldInfo(1, "<f4", "Pa",
                          "-tr(tau) / 3, Kirchhoff mean stress (compression > 0)"),
    "id": FieldInfo(1, "<i8", "1", "original particle id (row of the HDF5 output)"),
}


def colour_label(name: str) -> str:
    """What a view colouring particles by field `name` shows, with its unit: "displacement
    magnitude (m)" for a vector field, "pressure (Pa)", "id"; an unknown field's own name."""
    info = FIELDS.get(name)
    if info is None:
        return name
    shown = f"{name} magnitude" if info.components > 1 else name
    shown = shown.replace("_", " ")
    return shown if info.unit == "1" else f"{shown} ({info.unit})"
