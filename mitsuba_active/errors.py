"""The one exception type that the command line turns into a one-line message."""


class UserError(Exception):
    """Bad input from the user (a file, an option, a budget).

    The CLI prints ``error: <message>`` on one line and exits with code 2;
    library callers can catch it like any other exception.
    """
