"""Which photo pairs `jaxnerf-grid poses` matches (docs/POSES.md, "Choosing the matcher").

Pure functions of the photo names (and, for the GPS priors, of positions): the pair lists are
given to COLMAP's matcher of listed pairs (`pycolmap.match_image_pairs`), the GPS positions to
its spatial matcher and its mapper as pose priors (`pycolmap.PosePrior`).

- `sequential_pairs`: each photo with its next `overlap` in name order (the capture order of a
  flight) and, to close an orbit that ends where it began, the same neighbours across the end
  of the sequence (photo i with photo (i + k) mod n): COLMAP closes loops with a vocabulary
  tree, which is not shipped nor downloaded (the machine is offline), so the wrap-around pairs
  stand in for its loop detection on an orbit; plus COLMAP's quadratic overlap (photo i with
  i + 2^k), which reaches the photos of the orbit flown above or below.
- `pair_count`: the pairs of exhaustive matching, n (n - 1) / 2.
- `pairs_file_text`: the pair list in COLMAP's format (one "NAME1 NAME2" a line).
"""

from __future__ import annotations


def pair_count(num_photos: int) -> int:
    """The pairs exhaustive matching compares: n (n - 1) / 2."""
    return num_photos * (num_photos - 1) // 2


def sequential_pairs(names: list[str], overlap: int, wrap: bool = True, quadratic: bool = True) -> list[tuple]:
    """Pairs of `names` (in capture order) for sequential matching: photo i with photos i + 1
    .. i + overlap; with `wrap` also across the end of the sequence ((i + k) mod n: the last
    photos of an orbit with its first ones); with `quadratic` also with photos i + 2^j (2^j >
    overlap, j < log2 n; wrapped like the others). Returns sorted (name_a, name_b) pairs, each
    once, a before b in `names`."""
    n = len(names)
    steps = set(range(1, overlap + 1))
    if quadratic:
        step = 1
        while step < n:
            steps.add(step)
            step *= 2
    pairs = set()
    for i in range(n):
        for k in steps:
            if i + k >= n and not wrap:
                continue
            j = (i + k) % n
            if j != i:
                pairs.add((min(i, j), max(i, j)))
    return [(names[a], names[b]) for a, b in sorted(pairs)]


def pairs_file_text(pairs: list[tuple]) -> str:
    """COLMAP's list of image pairs: one "NAME_A NAME_B" a line (names without spaces)."""
    return "".join(f"{a} {b}\n" for a, b in pairs)
