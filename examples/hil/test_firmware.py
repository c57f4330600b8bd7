"""The controller says who it is."""

import repetrel_host as rh
from repetrel_host.session.planning import is_hyrel_firmware

# The built-in fake's name on each link (--hyrel-protocol).
FAKE_NAMES = {
    "reprap": "repetrel-host fake controller (Marlin replies)",
    "hyrel": ">Hy: repetrel-host-fake_1.0",
}


def test_the_controller_answers_m115_with_its_name(hyrel_printer, hyrel_controller):
    reply = hyrel_printer.command("M115")
    firmware = rh.Firmware.parse([*reply.lines, reply.ok_line])
    assert firmware is not None, f"M115 named no firmware: {reply.lines}"
    if hyrel_controller.is_fake:
        assert firmware.name == FAKE_NAMES[hyrel_printer.session.settings.protocol]
    else:
        assert is_hyrel_firmware(firmware.identity), f"not a Hyrel controller: {firmware.name}"
    # The session asked the same question when it connected.
    assert hyrel_printer.firmware == firmware
