"""Known errors. The command line turns any of these into one line and exit code 1;
anything else keeps its traceback (STYLE.md, habit 7). Each module subclasses the
base with an error of its own."""


class GridslamError(Exception):
    """Base of every error gridslam knows how to explain in one line."""


class ConfigError(GridslamError):
    """A preset, config file, environment variable or flag is missing or invalid."""


class DataError(GridslamError):
    """An input file or dataset is missing, unreadable or malformed (the message names it)."""


class PersistenceError(GridslamError):
    """A service cannot write the state it must keep (a journal, a checkpoint): it stops instead of
    going on with state a restart would lose (the message names the file)."""
