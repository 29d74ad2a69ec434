class ClrefractError(Exception):
    """An error the user can fix; the message names the file and the problem."""
