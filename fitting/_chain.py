"""The posterior chain: an emcee backend that is also a file, so that a run can be resumed.

`ChainBackend` is emcee's in-memory `Backend` (positions, log probabilities, acceptance counts
and the random state, exactly as emcee stores them) plus `save`: an atomic `.npz` file written
after every chunk, and `ChainBackend.load`, which restores a backend from that file. Handed to
`emcee.EnsembleSampler(..., backend=...)`, a restored backend continues the chain with
`sampler.run_mcmc(None, n)`, as emcee intends for its own `HDFBackend`. The file layout is in
docs/fitting.md ("Chain file"); `load_chain` reads it as a dict of arrays [conventions §10].
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import emcee
import numpy as np

from stairfit.fileio import atomic_path

from ._errors import FitInputError

CHAIN_FORMAT_VERSION = 1
"""Version of the chain file layout (docs/fitting.md, "Chain file"). Keys added since version
1 was introduced (`parameters`, `wedges`) are optional for readers."""


class ChainInfo(NamedTuple):
    """What a chain file records besides emcee's state (docs/fitting.md, "Chain file").

    `names`: display labels of the free parameters; `parameters`, `wedges`: their identity
    (`fitting.Parameter.param`, and the wedge of a per-wedge width or -1); `seed`: the seed of
    the first run; `free_slots`, `ls_z`: the layout of the unconstrained vector and the
    least-squares optimum; `fingerprint`: hash of what the log probability depends on;
    `variant`: the variant's name.
    """

    names: tuple[str, ...]
    parameters: tuple[str, ...]
    wedges: tuple[int, ...]
    seed: int
    free_slots: np.ndarray
    ls_z: np.ndarray
    fingerprint: str
    variant: str


def _pack_random_state(state: tuple) -> dict[str, np.ndarray]:
    """numpy's MT19937 state tuple (what emcee keeps) as arrays for `np.savez`."""
    _, keys, pos, has_gauss, cached = state
    return {
        "rng_keys": np.asarray(keys, dtype=np.uint32),
        "rng_pos": np.asarray(pos),
        "rng_has_gauss": np.asarray(has_gauss),
        "rng_cached_gaussian": np.asarray(cached),
    }


def _unpack_random_state(f: dict[str, np.ndarray]) -> tuple:
    return (
        "MT19937",
        f["rng_keys"],
        int(f["rng_pos"]),
        int(f["rng_has_gauss"]),
        float(f["rng_cached_gaussian"]),
    )


def save_npz(path: Path, payload: dict[str, np.ndarray]) -> None:
    """Write `payload` to `path` atomically (`stairfit.fileio.atomic_path`: a temporary file in
    the same folder, mode 0666 less the umask, then renamed; never a half-written file)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **payload)


class ChainBackend(emcee.backends.Backend):
    """emcee's in-memory backend, saved to and restored from a chain file.

    `info` describes the chain (`ChainInfo`); `path` is where `save` writes it (None: memory
    only). emcee fills `chain` (unconstrained positions), `log_prob`, `accepted` and
    `random_state` as it samples.
    """

    def __init__(self, info: ChainInfo, path: str | Path | None = None) -> None:
        super().__init__()
        self.info = info
        self.path = None if path is None else Path(path)

    @classmethod
    def load(cls, path: str | Path) -> ChainBackend:
        """A backend holding the chain of `path` (written by `save`), ready to continue."""
        f = load_chain(path)
        names = tuple(str(n) for n in f["names"])
        info = ChainInfo(
            names=names,
            parameters=tuple(str(n) for n in f.get("parameters", ())),
            wedges=tuple(int(w) for w in f.get("wedges", ())),
            seed=int(f["seed"]),
            free_slots=np.asarray(f["free_slots"]),
            ls_z=np.asarray(f["ls_z"]),
            fingerprint=str(f["fingerprint"]),
            variant=str(f["variant"]),
        )
        backend = cls(info, path)
        chain_z = np.asarray(f["chain_z"], dtype=backend.dtype)
        backend.reset(chain_z.shape[1], chain_z.shape[2])
        backend.chain = chain_z
        backend.log_prob = np.asarray(f["log_prob"], dtype=backend.dtype)
        backend.accepted = np.asarray(f["n_accepted"], dtype=backend.dtype)
        backend.random_state = _unpack_random_state(f)
        backend.iteration = chain_z.shape[0]
        return backend

    def save(self, physical: np.ndarray, tau: np.ndarray) -> None:
        """Write the chain so far atomically: a temporary file in the same folder, then
        `os.replace` (never a half-written file). `physical`: the chain in physical values
        `(n_steps, n_walkers, p)`; `tau`: the last autocorrelation estimate."""
        if self.path is not None:
            save_npz(self.path, self._payload(physical, tau))

    def _payload(self, physical: np.ndarray, tau: np.ndarray) -> dict[str, np.ndarray]:
        info = self.info
        return {
            "format_version": np.asarray(CHAIN_FORMAT_VERSION),
            "names": np.asarray(info.names),
            "parameters": np.asarray(info.parameters),
            "wedges": np.asarray(info.wedges, dtype=int),
            "chain": physical,
            "chain_z": self.get_chain(),
            "log_prob": self.get_log_prob(),
            "n_accepted": np.asarray(self.accepted),
            "seed": np.asarray(info.seed),
            **_pack_random_state(self.random_state),
            "free_slots": np.asarray(info.free_slots),
            "ls_z": np.asarray(info.ls_z),
            "tau": np.asarray(tau),
            "fingerprint": np.asarray(info.fingerprint),
            "variant": np.asarray(info.variant),
        }


def load_chain(path: str | Path) -> dict[str, np.ndarray]:
    """Read a chain file written by `sample_posterior` (see docs/fitting.md for the fields)."""
    path = Path(path)
    if not path.is_file():
        raise FitInputError(f"chain file {path} does not exist; run sample_posterior first")
    with np.load(path, allow_pickle=False) as f:
        out = {k: f[k] for k in f.files}
    version = int(out.get("format_version", -1))
    if version != CHAIN_FORMAT_VERSION:
        raise FitInputError(
            f"chain file {path}: format_version {version} is not {CHAIN_FORMAT_VERSION}; "
            "start a new chain"
        )
    return out
