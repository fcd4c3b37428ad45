"""Named, independent random streams from one scenario seed (docs/architecture.md,
"Frames and conventions").

Each stream is keyed by a path of names, e.g. ``("imu", "lru1")``; its generator is
derived from the scenario's ``SeedSequence`` and a stable hash of the path, so adding
a robot or a component never changes the numbers another stream draws. Every random
draw of a run comes from here: a generator from :meth:`RandomStreams.rng`, or for code
that takes an integer seed (the submap matcher) one from :meth:`RandomStreams.integer_seed`.
"""

from __future__ import annotations

import zlib

import numpy as np


class RandomStreams:
    def __init__(self, seed: int):
        self.seed = int(seed)

    def seed_sequence(self, *path: str) -> np.random.SeedSequence:
        key = [zlib.crc32("/".join(path).encode())] if path else []
        return np.random.SeedSequence([self.seed, *key])

    def rng(self, *path: str) -> np.random.Generator:
        """A fresh generator for ``path``; the same path always gives the same numbers."""
        return np.random.default_rng(self.seed_sequence(*path))

    def integer_seed(self, *path: str) -> int:
        """A 32-bit seed for ``path``, for code that seeds itself; the same path always gives the same seed."""
        return int(self.seed_sequence(*path).generate_state(1)[0])
