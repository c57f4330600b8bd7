"""Pure G-code knowledge: command classes (later: T addressing, lint)."""

from repetrel_host.gcode.commands import UNBUFFERED, command_word, is_unbuffered

__all__ = ["UNBUFFERED", "command_word", "is_unbuffered"]
