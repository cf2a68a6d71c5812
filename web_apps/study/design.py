"""Williams' balanced Latin square, the design's orders of conditions (`web_apps.study.assignment` fills a
participant's games from its rows; a config's check counts them)."""

from __future__ import annotations


def latin_square(n: int) -> list[list[int]]:
    """Williams' balanced Latin square over conditions 0..n-1: n rows for an even n, 2n (each row and its reverse)
    for an odd one. Each condition appears once per row and equally often at each position."""
    first, low, high = [0], 1, n - 1
    while len(first) < n:  # 0, 1, n-1, 2, n-2, ...
        first.append(low)
        low += 1
        if len(first) < n:
            first.append(high)
            high -= 1
    rows = [[(condition + shift) % n for condition in first] for shift in range(n)]
    return rows if n % 2 == 0 else rows + [row[::-1] for row in rows]
