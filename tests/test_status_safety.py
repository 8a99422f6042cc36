"""`topseg status`'s safety lines: a safety token is a cell's service, not a camera; its
states in the window give the state now, their counts, the reaction time and the reasons;
a safety service that went down is a problem, a `stop` is not."""

from topseg.core.formats.safety_wire import SafetyState
from topseg.services.live.status import Observed, exit_status, format_table, observed_tokens, report
from topseg.services.live.status_safety import format_safety, safety_rows


def state(seq, name, reaction=30.0, reasons=()):
    scale = 0.0 if name == "stop" else 1.0 if name == "clear" else 0.5
    return SafetyState(seq, 10**18 + seq, name, scale, 1.2, "hand", "link3", reaction, reasons)


def test_a_safety_token_is_the_cells_service_not_a_camera():
    tokens = {
        ("c1", "cam0", "driver", "a"),
        ("c1", "cam0", "worker", "b"),
        ("c1", "safety", "safety", "s"),
    }
    seen = observed_tokens(tokens, set())
    assert seen.safety_alive == {"c1"}
    assert ("c1", "safety", "safety") not in seen.alive
    rep = report(Observed(alive=seen.alive, safety_alive=seen.safety_alive, window_s=1.0))
    assert [r["camera"] for r in rep["cameras"]] == ["cam0"]
    assert rep["safety"][0]["alive"] and exit_status(rep) == 0


def test_states_in_the_window():
    got = [
        state(0, "clear", 20),
        state(1, "warning", 40),
        state(2, "stop", 60, ("hand 0.2 m from link3",)),
    ]
    (row,) = safety_rows({"c1"}, set(), {"c1": got}, 2.0)
    assert row["state"] == "stop" and row["states_in_window"] == {
        "clear": 1,
        "warning": 1,
        "stop": 1,
    }
    assert row["reaction_ms"] == {"p50": 40.0, "p99": 60.0} and row["rate_hz"] == 1.5
    assert row["reasons"] == ["hand 0.2 m from link3"]
    lines = format_safety([row])
    assert "STOP now" in lines[0] and "reaction p50/p99 40/60 ms" in lines[0]
    assert lines[1].endswith("why: hand 0.2 m from link3")


def test_a_stop_is_not_a_problem_but_a_service_that_went_down_is():
    stop = report(Observed(safety_alive={"c1"}, safety={"c1": [state(0, "stop")]}, window_s=1.0,
                           alive={("c1", "cam0", "driver"), ("c1", "cam0", "worker")}))  # fmt: skip
    assert exit_status(stop) == 0
    down = report(Observed(safety_went_down={"c1"}, window_s=1.0,
                           alive={("c1", "cam0", "driver"), ("c1", "cam0", "worker")}))  # fmt: skip
    assert exit_status(down) == 1
    assert "safety c1: went down during the window" in format_table(down)


def test_reasons_from_the_wire_are_printed_escaped():
    row = safety_rows(
        {"c1"}, set(), {"c1": [state(0, "stop", reasons=("\x1b[2Jfake\nline",))]}, 1.0
    )[0]
    text = "\n".join(format_safety([row]))
    assert "\x1b" not in text and "fake\nline" not in text
