"""Resource bounds of the input files, and the warning category of the
physical plausibility checks (issue 25, items 7 and 9).

Every size a robot, scenario, plan or study file can ask for is checked
against one of the limits below BEFORE anything is allocated, and a file
over a limit is refused with an error naming the field, the value and the
limit ("segments[0].sections: 1000000 exceeds the limit of 500"). The
limits are set far above what a real user asks for, and below what would
exhaust the memory or the patience of an ordinary machine:

- MAX_FILE_BYTES (16 MiB): the shipped robot, scenario, plan and study
  files are 1-10 KB; a robot file with a few hundred bodies is ~100 KB.
- MAX_NESTING (64 levels of lists/mappings): the deepest shipped file nests
  4 levels; YAML parsing recurses per level, so 5,000 levels would end in a
  RecursionError.
- MAX_SECTIONS_PER_SEGMENT (500) and MAX_SECTIONS_TOTAL (1000): PCS
  converges with 5-50 sections per segment (convergence studies in the
  tests go to 64); the dense dynamics matrices grow as (6 n)^2, so 1000
  sections already mean 6000 x 6000 matrices (288 MB each).
- MAX_TIME_STEPS (10 million): duration / dt of a dynamics run or a plan's
  dynamic check; 10^7 steps of 1 ms are 2.8 simulated hours (days of wall
  time for the rod model).
- MAX_RECORDED_ROWS (2 million) and MAX_BACKBONE_POINTS (50 million): the
  output samples a run keeps in memory (time-history rows; backbone points,
  24 bytes each and more in JSON); MAX_POINTS_PER_SECTION (1000) the
  backbone points drawn per section (10 by default).
- MAX_PATH_SAMPLES (1 million): duration / sample_period of a planned tip
  path (each sample is an IK solve: about a second each).
- MAX_STUDY_SAMPLES (1 million): cases of a study (each case is a solve;
  a million takes days on a cluster); also bounds a workspace's samples.
- MAX_BODIES (2000): bodies, joints, frames or members of a tree robot.
"""

import os

MAX_FILE_BYTES = 16 * 1024 * 1024
MAX_NESTING = 64
MAX_SECTIONS_PER_SEGMENT = 500
MAX_SECTIONS_TOTAL = 1000
MAX_TIME_STEPS = 10_000_000
MAX_RECORDED_ROWS = 2_000_000
MAX_BACKBONE_POINTS = 50_000_000
MAX_POINTS_PER_SECTION = 1000
MAX_PATH_SAMPLES = 1_000_000
MAX_STUDY_SAMPLES = 1_000_000
MAX_BODIES = 2000


class PlausibilityWarning(UserWarning):
    """A robot file value is allowed but physically implausible; the
    message names the field and the likely unit slip (mm for m, MPa for
    Pa, degrees for radians)."""


def over_limit(field, value, limit, unit=""):
    """The message of a value over a resource limit."""
    v = f"{value:g}" if isinstance(value, float) else f"{value}"
    return f"{field}: {v}{unit} exceeds the limit of {limit}{unit} (soft_twin_core.limits)"


def check_limit(field, value, limit, error, unit=""):
    """Raise ``error`` if ``value > limit``."""
    if value > limit:
        raise error(over_limit(field, value, limit, unit))


def read_text(path, error, what):
    """The text of ``path``, refused with ``error`` naming the file when it
    is larger than MAX_FILE_BYTES (checked before reading) or not UTF-8
    text (a binary file)."""
    try:
        size = os.stat(path).st_size
    except OSError as e:
        raise error(f"{what} {path}: {e.strerror}") from None
    if size > MAX_FILE_BYTES:
        raise error(f"{what} {path}: {size} bytes exceeds the limit of {MAX_FILE_BYTES} bytes "
                    f"(soft_twin_core.limits; is it the right file?)")
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except OSError as e:
        raise error(f"{what} {path}: {e.strerror}") from None
    if len(data) > MAX_FILE_BYTES:
        raise error(f"{what} {path}: more than {MAX_FILE_BYTES} bytes exceeds the limit "
                    f"(soft_twin_core.limits; is it the right file?)")
    return decode_text(data, path, error, what)


def decode_text(data, path, error, what):
    """``data`` (bytes) as UTF-8 text, else ``error`` naming the file."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{what} {path}: not a text file (invalid UTF-8 byte 0x{data[e.start]:02x} at "
                    f"offset {e.start}); expected YAML") from None
    if "\x00" in text:
        raise error(f"{what} {path}: not a text file (a NUL byte at offset {text.index(chr(0))}); "
                    f"expected YAML")
    return text


def check_yaml_nesting(text, source, error):
    """Refuse YAML nested deeper than MAX_NESTING before it is parsed (the
    scanner is iterative; the parser would recurse per level)."""
    import yaml
    starts = (yaml.BlockSequenceStartToken, yaml.BlockMappingStartToken,
              yaml.FlowSequenceStartToken, yaml.FlowMappingStartToken)
    ends = (yaml.BlockEndToken, yaml.FlowSequenceEndToken, yaml.FlowMappingEndToken)
    depth = 0
    try:
        for tok in yaml.scan(text, Loader=yaml.SafeLoader):
            if isinstance(tok, starts):
                depth += 1
                if depth > MAX_NESTING:
                    line = tok.start_mark.line + 1
                    raise error(f"{source}: nesting deeper than {MAX_NESTING} levels (line {line}) "
                                f"exceeds the limit of {MAX_NESTING} (soft_twin_core.limits)")
            elif isinstance(tok, ends):
                depth -= 1
    except yaml.YAMLError:
        return          # the parser reports the syntax error itself


def load_yaml_text(text, source, error):
    """Parsed YAML of ``text`` (nesting checked first); ``error`` naming
    ``source`` for bad YAML."""
    import yaml
    check_yaml_nesting(text, source, error)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise error(f"{source}: invalid YAML: {e}") from None
    except RecursionError:          # belt and braces: aliases can nest too
        raise error(f"{source}: nesting too deep (the limit is {MAX_NESTING} levels)") from None
