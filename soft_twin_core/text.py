"""Bounded text from user input, for log lines, diagnostics and replies.

Every string the node logs, puts in /diagnostics or sends back that holds
something a user sent (actuator names, a frame id, a parameter value, an
exception message quoting them) goes through :func:`clip` or
:func:`short_list`, so a hostile or mistaken input (a command with 10,000
names, a 100 kB frame id) cannot produce a 100 kB log line repeated every
second. ROS-free.
"""

LIMIT = 200      # characters kept of one piece of user input


def clip(text, limit=LIMIT):
    """``text`` (any object: str() of it) cut to ``limit`` characters, with
    "... (N more characters)" saying what was left out."""
    text = str(text)
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text) - limit} more characters)"


def short_list(items, limit=LIMIT):
    """A list's repr with as many items as fit in about ``limit`` characters
    (each item clipped too), then "... (N more)" for the items left out."""
    items = list(items)
    shown, used = [], 2
    for item in items:
        r = repr(clip(item, limit) if isinstance(item, str) else item)
        if shown and used + len(r) + 2 > limit:
            break
        shown.append(r)
        used += len(r) + 2
    text = "[" + ", ".join(shown) + "]"
    if len(shown) < len(items):
        text += f" ... ({len(items) - len(shown)} more)"
    return text
