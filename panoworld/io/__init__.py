"""One reader and one writer per artifact kind (panoworld/io/<kind>.py); JSON with one policy for non-finite numbers."""

from panoworld.io.jsonio import read_json, to_jsonable, write_json  # noqa: F401  (the package's API)
from panoworld.io.jsonl import read_jsonl, write_jsonl  # noqa: F401
