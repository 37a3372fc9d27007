"""Random state of one's own, for the networks that sit beside SB3's (predictor, synthetic oracle)."""

import contextlib
import copy
from collections.abc import Iterator
from typing import Any, Optional

import numpy as np
import torch


class OwnRandomState:
    """Mixin: a numpy generator and a torch generator state of the object's own.

    Torch's random ops inside ``with self._torch_rng():`` (weight initialisation, dropout masks,
    shuffling) draw from the object's state and leave the global one untouched, so the object is
    reproducible from its seed and does not disturb SB3's seeding. Needs ``self.device``.
    """

    device: torch.device

    def _init_random_state(self, seed: Optional[int]) -> None:
        if seed is None:  # drawn from the global state, so SB3's set_random_seed still decides it
            seed = int(torch.randint(0, 2**31 - 1, (1,)).item())
        self.seed = int(seed)
        self._np_rng = np.random.default_rng(self.seed)
        self._cpu_rng_state = torch.Generator().manual_seed(self.seed).get_state()
        self._cuda_rng_state: Optional[torch.Tensor] = None
        if self.device.type == "cuda":
            self._cuda_rng_state = torch.Generator(device=self.device).manual_seed(self.seed).get_state()

    def _cuda_index(self) -> int:
        return self.device.index if self.device.index is not None else torch.cuda.current_device()

    @contextlib.contextmanager
    def _torch_rng(self) -> Iterator[None]:
        """Run torch's random ops on the object's own generator state, leaving the global one untouched."""
        cuda = self._cuda_rng_state is not None
        with torch.random.fork_rng(devices=[self._cuda_index()] if cuda else []):
            torch.set_rng_state(self._cpu_rng_state)
            if cuda:
                torch.cuda.set_rng_state(self._cuda_rng_state, self._cuda_index())
            try:
                yield
            finally:
                self._cpu_rng_state = torch.get_rng_state()
                if cuda:
                    self._cuda_rng_state = torch.cuda.get_rng_state(self._cuda_index())

    def _random_state_dict(self) -> dict[str, Any]:
        return {
            "np_rng": copy.deepcopy(self._np_rng.bit_generator.state),
            "torch_rng": self._cpu_rng_state.clone(),
            "cuda_rng": None if self._cuda_rng_state is None else self._cuda_rng_state.clone(),
        }

    def _load_random_state_dict(self, state: dict[str, Any]) -> None:
        self._np_rng.bit_generator.state = copy.deepcopy(state["np_rng"])
        self._cpu_rng_state = state["torch_rng"].clone()
        if self._cuda_rng_state is not None and state.get("cuda_rng") is not None:
            self._cuda_rng_state = state["cuda_rng"].clone()
