"""How every command of the project ends: an exit status and one line on stderr, no traceback.

Exit status: 0 on success, 2 for a bad file, key or argument (the message names it), 1 for
anything else. COMPANION_DEBUG=1 shows tracebacks.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from companion.errors import CompanionError, ConfigError

EXIT_OK, EXIT_ERROR, EXIT_USAGE = 0, 1, 2


def run_command(prog: str, body: Callable[[], int]) -> int:
    """Run a command's body; errors become one line on stderr and an exit status, no traceback.

    ConfigError (a bad file, key or argument) exits 2; any other error exits 1, with the
    traceback only when COMPANION_DEBUG is set.
    """
    try:
        return body()
    except ConfigError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_ERROR
    except (CompanionError, OSError) as exc:
        if os.environ.get("COMPANION_DEBUG"):
            raise
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except Exception as exc:  # the last line of defence: no traceback at a user
        if os.environ.get("COMPANION_DEBUG"):
            raise
        print(f"{prog}: internal error: {type(exc).__name__}: {exc} "
              "(set COMPANION_DEBUG=1 for the traceback)", file=sys.stderr)
        return EXIT_ERROR
