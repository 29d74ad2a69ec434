class ClrefractError(Exception):
    """An error the user can fix; the message names the file and the problem."""


class BuildError(ClrefractError):
    """An OpenCL program that a driver could not build; `compiler_error` is its first error."""

    def __init__(self, message: str, compiler_error: str):
        super().__init__(message)
        self.compiler_error = compiler_error
