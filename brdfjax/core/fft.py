"""FFT sizes: the one helper that picks a fast length for the footprint convolutions (fit and synthetic camera)."""

from __future__ import annotations

__all__ = ["fast_len"]


def fast_len(n: int) -> int:
    """The smallest ``2^a 3^b 5^c >= n`` (at least 1): a length NumPy's and XLA's FFTs handle fast.

    Enumerates the 5-smooth candidates below the next power of two (a few dozen for any frame size) rather
    than testing ``n, n+1, ...`` one by one.  Equals ``scipy.fft.next_fast_len(n, real=True)``.
    """
    n = max(int(n), 1)
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best
