"""A small job streams, and runs exactly once, even over a noisy link."""

SQUARE = """\
G28 ; home
G90
G1 Z5 F600
G1 X10 Y10 F3000
G1 X30 Y10
G1 X30 Y30
G1 X10 Y30
G1 X10 Y10
G1 Z10 F600
"""


# The fake's noise, as each link may have it: Hyrel's has no resend, so a corrupted line
# stops the job there; ACK bytes lost and replies garbled it survives.
NOISE = {"reprap": "corrupt=0.05 drop_ok=0.05 seed=11", "hyrel": "drop_ok=0.1 garble=0.05 seed=11"}


def test_a_small_job_runs_exactly_once(hyrel_printer, hyrel_controller, hyrel_job):
    job = hyrel_job(SQUARE, header=False)
    protocol = hyrel_printer.session.settings.protocol
    if hyrel_controller.is_fake:  # ignored on the bench
        hyrel_controller.set_faults(NOISE[protocol])
    before = len(hyrel_controller.executed) if hyrel_controller.is_fake else 0
    result = hyrel_printer.print(job)
    assert result.completed
    assert result.acknowledged == result.commands  # every line, in order
    assert len(result.commands) == 9
    if hyrel_controller.is_fake:  # only the fake can tell what it executed
        assert hyrel_controller.executed[before:] == result.commands
