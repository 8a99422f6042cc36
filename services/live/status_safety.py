"""`topseg status`'s lines for the cells' safety services: alive or DOWN, the state now, how
often each state held in the window, decisions per second, reaction time p50/p99 and the
reasons of the last decision that was not `clear`.

A safety service holds `topseg/<cell>/safety/alive/safety/<instance>` (a token of the shape
every service holds, `safety_wire.safety_alive_key`) and publishes `topseg/<cell>/safety`.
A `stop` is the cell's state, not a fault of the service: it does not change the exit status;
a safety service that went DOWN in the window does.
"""

from __future__ import annotations

from topseg.core.formats.safety_wire import SAFETY, STATES, SafetyState
from topseg.core.metrics import percentile
from topseg.core.printable import printable

#: The longest reason shown.
MAX_REASON_TEXT = 160


def is_safety_token(camera: str, role: str | None) -> bool:
    """Whether a parsed token (`wire.parse_key`) is a safety service's, not a camera's."""
    return camera == SAFETY and role == SAFETY


def safety_rows(alive: set[str], went_down: set[str], states: dict[str, list[SafetyState]],
                window_s: float) -> list[dict]:  # fmt: skip
    """One JSON-able row per cell with a safety service seen (token or messages)."""
    rows = []
    for cell in sorted(alive | went_down | set(states)):
        got = sorted(states.get(cell, []), key=lambda s: s.seq)
        row: dict = {
            "cell": cell,
            "alive": cell in alive,
            "went_down": cell in went_down and cell not in alive,
            "decisions_in_window": len(got),
            "rate_hz": round(len(got) / window_s, 1) if window_s > 0 else 0.0,
        }
        if got:
            last = got[-1]
            row["state"] = last.state
            row["speed_scale"] = last.speed_scale
            row["min_distance_m"] = last.min_distance_m
            row["states_in_window"] = {s: sum(g.state == s for g in got) for s in STATES}
            reactions = [g.reaction_ms for g in got if g.reaction_ms is not None]
            if reactions:
                row["reaction_ms"] = {
                    "p50": round(percentile(reactions, 50), 1),
                    "p99": round(percentile(reactions, 99), 1),
                }
            strict = [g for g in got if g.state != "clear" and g.reasons]
            if strict:
                row["reasons"] = list(strict[-1].reasons)
        rows.append(row)
    return rows


def safety_ok(rows: list[dict]) -> bool:
    """False when a safety service went down in the window."""
    return not any(r["went_down"] for r in rows)


def format_safety(rows: list[dict]) -> list[str]:
    """The rows as lines for people (none when there is no safety service)."""
    lines = []
    for r in rows:
        alive = "alive" if r["alive"] else "DOWN"
        text = f"safety {r['cell']}: {alive}"
        if "state" in r:
            share = " ".join(f"{s} {n}" for s, n in r["states_in_window"].items() if n)
            dist = r["min_distance_m"]
            lat = r.get("reaction_ms", {})
            text += (
                f", {r['state'].upper() if r['state'] == 'stop' else r['state']} now "
                f"(speed {r['speed_scale']:.2f}"
                + (f", person {dist:.2f} m" if dist is not None else "")
                + f"), {r['rate_hz']:.1f}/s [{share}]"
                + (f", reaction p50/p99 {lat['p50']:.0f}/{lat['p99']:.0f} ms" if lat else "")
            )
        else:
            text += ", no decision in the window"
        lines.append(text)
        if r.get("reasons"):
            lines.append(
                f"safety {r['cell']}: why: " + printable("; ".join(r["reasons"]), MAX_REASON_TEXT)
            )
        if r["went_down"]:
            lines.append(f"safety {r['cell']}: went down during the window")
    return lines
