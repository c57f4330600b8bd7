"""The loadout's header (M6, M721, M722, M221, M728 for every head) is accepted."""


def test_every_header_line_is_accepted(hyrel_printer, hyrel_job):
    result = hyrel_printer.print(hyrel_job("G4 P0\n"))
    assert result.header, "no header: name a loadout (hyrel_loadout in pytest.ini)"
    assert result.header_acknowledged == result.header
    assert result.completed
    words = [command.split()[0] for command in result.header]
    for word in ("M6", "M721", "M722", "M221", "M728"):
        assert word in words, f"the header has no {word}: {result.header}"
