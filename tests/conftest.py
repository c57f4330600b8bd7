import pytest

from tests.helpers import CONE, job_commands


@pytest.fixture(scope="session")
def cone_commands() -> list[str]:
    commands = job_commands(CONE)
    assert len(commands) > 20_000
    return commands
