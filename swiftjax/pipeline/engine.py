"""The live engine: a reconstruction fed frame by frame and polled for poses.

::

    rec = Reconstruction("runs/live", predictor, config)
    for image in camera:                      # or rec.add_frame() when the predictor knows its frames
        rec.add_frame(image, time=stamp)
        frames, cam_to_world = rec.poses()    # [F], [F, 4, 4]: every frame posed so far
    result = rec.finish()                     # the offline run of the same frames

Each time the frames complete a chunk of the offline schedule (``n = B + k (B - O)``), the
stages of :func:`~swiftjax.pipeline.run.reconstruct` run over the frames seen so far, in the
run directory (:class:`Prefix`: the run directory's "frames added" resume keeps every chunk
already predicted, predicting the new chunk and re-predicting the one before it, whose float32
overlap the new edge needs).  The new frames' poses are appended to ``poses_live.jsonl``
(:mod:`~swiftjax.pipeline.live`); when a newly accepted loop closes, the trajectory's revision
increases and every frame is published again.  :meth:`Reconstruction.finish` is the same
``reconstruct`` over every frame: the finished run directory is the offline run's (plus
``poses_live.jsonl``), and its poses are published once more as the ``"final"`` revision.

Cost: every live step re-runs loop detection, the loop chunks, the pose graph and the export over
the prefix (the loop chunks and the export's files grow with the prefix); the stages that keep
their state between steps are issue 30's next step.
"""

from __future__ import annotations

import logging
import pathlib
from collections.abc import Callable
from typing import Any

import numpy as np

from swiftjax.pipeline.config import PipelineConfig
from swiftjax.pipeline.live import LiveLog
from swiftjax.pipeline.results import RunResult
from swiftjax.pipeline.run import reconstruct

__all__ = ["Prefix", "Reconstruction"]


class Prefix:
    """The first ``n`` frames of ``predictor`` as a predictor of their own.

    Its fingerprint lists the frames one by one (the predictor's own items, else its frame
    names), so that a run directory written for fewer frames is resumed as "frames added"."""

    def __init__(self, predictor: Any, n: int) -> None:
        if not 1 <= n <= int(predictor.num_frames):
            raise ValueError(f"a prefix of {n} frames of a predictor with {predictor.num_frames}")
        self.inner, self.num_frames = predictor, int(n)

    def predict(self, frames: np.ndarray) -> Any:
        if len(frames) and int(np.max(frames)) >= self.num_frames:
            raise ValueError(f"frame {int(np.max(frames))} is not among the first {self.num_frames}")
        return self.inner.predict(frames)

    def fingerprint(self) -> dict[str, Any]:
        fp = dict(self.inner.fingerprint())
        frames = fp.pop("frames", None)
        items = list(frames[: self.num_frames]) if frames is not None else [[name] for name in self.frame_names()]
        return {"frames": items, **fp}

    def frame_names(self) -> list[str]:
        return list(self.inner.frame_names())[: self.num_frames]

    def __getattr__(self, name: str) -> Any:  # images, source, mode, prefetch ...: the inner predictor's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


class Reconstruction:
    """A run fed one frame at a time (see the module docstring).

    ``predictor``: the whole input's predictor; its frames become usable as they are added
    (``add_frame(image)`` hands the image to ``predictor.append`` for a predictor on a growing
    frame source; a predictor that knows its frames, e.g. the synthetic oracle, takes
    ``add_frame()``).  ``ground_truth [N, 4, 4]``: optional, for the runs' metrics.
    ``timestamps_note``: where the ``time`` given to :meth:`add_frame` comes from
    (``poses_tum.txt``'s header, as ``reconstruct``'s).
    """

    def __init__(
        self,
        run_dir: str | pathlib.Path,
        predictor: Any,
        config: PipelineConfig = PipelineConfig(),
        *,
        ground_truth: np.ndarray | None = None,
        executor: Any = None,
        overwrite: bool = False,
        log: Callable[[str], None] = logging.getLogger(__name__).info,
        timestamps_note: str | None = None,
    ) -> None:
        self.run_dir, self.predictor, self.config = pathlib.Path(run_dir), predictor, config
        self.ground_truth, self.executor, self.overwrite, self.log = ground_truth, executor, overwrite, log
        self.timestamps_note = timestamps_note
        self.num_frames = 0
        self.times: list[float] = []
        self._timed = False  # a time was given (else poses_tum.txt says: the frame index)
        self.revision = 0
        self.result: RunResult | None = None  # the last step's run
        self._cam_to_world = np.zeros((0, 4, 4))
        self._accepted = 0
        self._live: LiveLog | None = None

    def add_frame(self, frame: Any = None, time: float | None = None) -> bool:
        """Add the next frame (``time``: seconds; default its index); True when it completed a
        chunk and the poses were updated."""
        if frame is not None:
            append = getattr(self.predictor, "append", None)
            if append is None:
                raise TypeError(f"{type(self.predictor).__name__} takes no frames (no append()); call add_frame()")
            append(frame)
        if self.num_frames >= int(self.predictor.num_frames):
            raise ValueError(f"frame {self.num_frames} added, but the predictor has {self.predictor.num_frames} frames")
        self.num_frames += 1
        self.times.append(float(self.num_frames - 1) if time is None else float(time))
        self._timed |= time is not None
        B, O = self.config.chunk_size, self.config.overlap
        n = self.num_frames
        if n < B or (n - B) % (B - O):
            return False
        self._step("loop closure")
        return True

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(frames [F], cam_to_world [F, 4, 4])`` of every frame posed so far (latest revision)."""
        return np.arange(len(self._cam_to_world)), self._cam_to_world.copy()

    def finish(self) -> RunResult:
        """The final pass: the offline run of every frame added; its poses published as the
        ``"final"`` revision."""
        if self.num_frames == 0:
            raise ValueError("no frame was added: nothing to reconstruct")
        try:
            self._step("final")
        finally:
            if self._live is not None:
                self._live.close()
                self._live = None
        assert self.result is not None
        return self.result

    def _step(self, revise: str) -> None:
        n = self.num_frames
        gt = None if self.ground_truth is None else np.asarray(self.ground_truth)[:n]
        result = reconstruct(
            Prefix(self.predictor, n),
            self.run_dir,
            self.config,
            ground_truth=gt,
            overwrite=self.overwrite,
            progress=False,
            timestamps=self.times if self._timed else None,
            timestamps_note=self.timestamps_note,
            log=self.log,
            executor=self.executor,
        )
        self.overwrite = False  # the first step replaced what was there
        if self._live is None:
            self._live = LiveLog(self.run_dir)
        c2w, old = result.cam_to_world, len(self._cam_to_world)
        accepted = len(result.loops)
        if revise == "final" or (accepted > self._accepted and old):
            self.revision += 1
            self._live.append(range(n), self.times, c2w, self.revision, revise)
        else:
            self._live.append(range(old, n), self.times[old:], c2w[old:], self.revision, "new")
            c2w = np.concatenate([self._cam_to_world, c2w[old:]])  # the published poses stand until a revision
        self._cam_to_world, self._accepted, self.result = c2w, accepted, result
