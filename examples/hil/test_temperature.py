"""The bed reaches its target within a deadline."""

import pytest

TARGET = 40.0


@pytest.mark.hyrel_fake(heat_rate=10)  # the fake's heaters take time too (ignored on the bench)
def test_the_bed_reaches_its_target_in_time(hyrel_printer):
    hyrel_printer.command(f"M140 S{TARGET:g}")
    try:
        reading = hyrel_printer.wait_for_temperature("B", TARGET, tolerance=2, timeout=180)
    finally:
        hyrel_printer.command("M140 S0")
    assert abs(reading - TARGET) <= 2
