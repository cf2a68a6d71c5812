"""The suite's own order (tests/conftest.py): its files longest first by their recorded seconds, so that make test's
two workers end together."""

import json

from conftest import DURATIONS


def test_the_files_run_longest_first_by_their_recorded_seconds_and_unknown_files_before_them(request):
    seconds = json.loads(DURATIONS.read_text())
    files = list(dict.fromkeys(item.nodeid.partition("::")[0] for item in request.session.items))
    known = [path for path in files if path in seconds]
    assert [seconds[path] for path in known] == sorted((seconds[path] for path in known), reverse=True)
    assert files == [path for path in files if path not in seconds] + known
    assert len(files) == len(set(files)), "each file's tests stay together"
