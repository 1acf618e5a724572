"""One reader and one writer per artifact kind (panoworld/io/<kind>.py); JSON with one policy for non-finite numbers
(jsonio, jsonl)."""
