"""The open-loop tracking world: simulate -> measure -> filter -> per-step sums.

``lanes`` (what a compared filter is: structure, realisation, sharing), ``errors`` (errors
and sums), ``scan`` (the chunk's scan, the world the runner drives), ``outcome`` (the
Monte-Carlo result), ``recorded`` (recorded data judged like a simulation), ``experiment``
(an open-loop experiment file's experiment).
"""
