"""What an evaluation run keeps so that a variant computes only what it changes: the run's caches,
behind one object that the predictor of each variant consults.

- **Clean predictions** (docs/evaluation.md "Reusing clean predictions"): the clean variant's
  detections. With ``reuse``, a frame of an attack variant whose whole model input the attack
  leaves untouched takes its clean prediction (bitwise what the model would return); with or
  without, every attack variant's confidence is scored against them.
- **Clean proposals** (models with a proposal history, PTT): the clean variant's proposal bank
  (:class:`~pcdet_atlas.train_utils.proposal_bank.ProposalBank`); a reusing attack variant's bank
  starts from the frames whose whole RPN batch the attack leaves untouched.
- **Prediction store** (docs/evaluation.md "Sharing the RPN between models"): a
  :class:`~pcdet_atlas.models.prediction_store.PredictionStore` that the model or its RPN reads
  and fills by their inputs; counted per variant.

One :class:`EvalCaches` per run (its clean run forgotten at each new checkpoint);
:meth:`EvalCaches.for_variant` gives one variant's loader what it reads and gives back
(:class:`VariantCache`, read by :func:`~pcdet_atlas.train_utils.eval_utils.predict_dataset`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.datasets.proposal_history import PROPOSAL_COLUMNS
from pcdet_atlas.models.prediction_store import PredictionStore
from pcdet_atlas.train_utils.dist import all_gather_objects
from pcdet_atlas.train_utils.proposal_bank import ProposalBank, frame_batches

__all__ = ["EvalCaches", "VariantCache", "check_proposals"]


def check_proposals(proposals, source: str) -> None:
    """Check proposals read back (``source``: their file, named in errors) against the layout of
    :meth:`~pcdet_atlas.train_utils.proposal_bank.ProposalBank.seedable`:
    ``{(sequence_name, sample_idx): float32 (R, 11) rows}``.

    Raises:
        ValueError: naming ``source``, the key and what was expected.
    """
    if not isinstance(proposals, Mapping):
        raise ValueError(
            f"{source}: expected a dict {{(sequence_name, sample_idx): (R, {PROPOSAL_COLUMNS}) "
            f"float32 rows}}, got {type(proposals).__name__}"
        )
    for key, rows in proposals.items():
        if not (
            isinstance(key, tuple) and len(key) == 2 and isinstance(key[0], str)
            and isinstance(key[1], int) and not isinstance(key[1], bool)
        ):  # fmt: skip
            raise ValueError(f"{source}: key {key!r} is not a (sequence_name, sample_idx) pair")
        if not (
            isinstance(rows, np.ndarray) and rows.dtype == np.float32 and rows.ndim == 2
            and rows.shape[1] == PROPOSAL_COLUMNS
        ):  # fmt: skip
            got = (f"{rows.dtype} array of shape {rows.shape}" if isinstance(rows, np.ndarray)
                   else type(rows).__name__)  # fmt: skip
            raise ValueError(
                f"{source}[{key!r}]: expected float32 rows of shape (R, {PROPOSAL_COLUMNS}), "
                f"got {got}"
            )


@dataclass(frozen=True)
class VariantCache:
    """What the predictor of one variant's loader reads from the run's caches and gives back.

    ``batches``: the loader's batches over all processes (indices into ``dataset.infos``), with
    which a proposal bank proposes each frame; ``reused``: predictions (anno dicts with
    ``frame_id``) standing for the frames the loader does not yield; ``proposal_seed``: the
    proposals a bank starts from; ``proposals_out``: receives the bank's proposals at the end
    (the clean variant's, kept for the others).
    """

    batches: Sequence[Sequence[int]] | None = None
    reused: Sequence[dict] | None = None
    proposal_seed: Mapping | None = None
    proposals_out: dict | None = None

    def seed(self, bank: ProposalBank) -> None:
        """Start ``bank`` from the proposals this variant may take from the clean run."""
        if self.proposal_seed:
            bank.seed(self.proposal_seed)

    def keep(self, bank: ProposalBank) -> None:
        """Give ``bank``'s proposals back to the run (the clean variant)."""
        if self.proposals_out is not None:
            self.proposals_out.update(bank.seedable())


class EvalCaches:
    """The caches of one evaluation run (module docstring).

    Args:
        reuse: let a frame whose whole input an attack leaves untouched take its clean
            prediction (and a bank start from the clean proposals); False runs every frame.
        store: the prediction store the model (or its RPN) uses (``use_prediction_store``),
            counted per variant; None without one.
    """

    def __init__(self, *, reuse: bool = True, store: PredictionStore | None = None):
        self.reuse = bool(reuse)
        self.store = store
        self.clean_predictions: list[dict] | None = None
        self.clean_proposals: dict = {}

    def new_checkpoint(self) -> None:
        """Forget the clean run of the checkpoint evaluated before."""
        self.clean_predictions = None
        self.clean_proposals = {}

    def keep_clean(
        self, det_annos: list[dict], proposals: Mapping | None = None, *, source: str = "proposals"
    ) -> None:
        """The clean variant's detections (and a process's clean proposals, read back by a
        resumed call from ``source``: checked by :func:`check_proposals`), for the variants
        after it."""
        self.clean_predictions = det_annos
        if proposals is not None:
            check_proposals(proposals, source)
            self.clean_proposals.update(proposals)

    def reuses_clean(self) -> bool:
        """Whether an attack variant evaluated now takes the clean predictions of the frames it
        leaves untouched."""
        return self.reuse and self.clean_predictions is not None

    def for_variant(
        self,
        dataset,
        batches: Sequence[Sequence[int]],
        rpn_input_attacked: Callable[[str, int], bool],
    ) -> VariantCache:
        """What the loader of one variant (``dataset``; ``batches``: its loader's batches over
        all processes) reads and gives back. The clean variant's bank gives its proposals back;
        a reusing attack variant's starts from the clean proposals of the frames whose whole RPN
        batch (:func:`~pcdet_atlas.train_utils.proposal_bank.frame_batches`) has RPN inputs the
        attack leaves untouched (``rpn_input_attacked(sequence, sample_idx)`` False), so that
        only the other frames go through the RPN again (still bitwise a full run)."""
        reuse = self.reuses_clean()
        seed = out = None
        if dataset.attack.family == "clean":
            out = self.clean_proposals
        elif self.clean_proposals and reuse:
            batch_of = frame_batches(dataset, batches)  # a frame no batch holds is proposed alone
            seed = {
                frame: rows for frame, rows in self.clean_proposals.items()
                if not any(rpn_input_attacked(*member) for member in batch_of.get(frame, (frame,)))
            }  # fmt: skip
        return VariantCache(
            batches=batches, reused=self.clean_predictions if reuse else None,
            proposal_seed=seed, proposals_out=out,
        )  # fmt: skip

    def store_counts(self) -> dict[str, int] | None:
        """This process's prediction-store counts now (None without a store)."""
        return self.store.counts() if self.store is not None else None

    def store_counts_since(self, before: Mapping[str, int] | None) -> dict[str, int] | None:
        """The store's batches served (``hits``) and stored (``misses``) by all processes since
        ``before`` (:meth:`store_counts`); every process calls it."""
        if self.store is None:
            return None
        mine = {k: v - before[k] for k, v in self.store.counts().items()}
        parts = all_gather_objects(mine)  # every process's batches
        return {k: sum(part[k] for part in parts) for k in mine}
