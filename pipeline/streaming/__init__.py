"""A capture or recording reconstructed as a stream of frame chunks, straight into the store.

``iristac reconstruct`` and ``iristac batch`` both come here. A recording of any length is read,
solved, integrated and written a chunk of frames at a time, so memory does not grow with it:

1. **plan** (:func:`~pipeline.streaming.plan.plan_stream`): the capture is opened without reading its frames (its
   large datasets stay on disk, :class:`pipeline.base.store.LazyDataset`), the light model
   loaded, and the keys of the results computed as the stages compute them
   (:func:`pipeline.stages.normals.key_params`, :mod:`pipeline.stages.depth`; the contact mask's
   entry on the depth entry and the capture): the same work through ``run``, ``reconstruct`` or
   ``batch`` is one cache entry. A complete entry is read back, not recomputed. Another unit's
   colours (``match_colours``): one gain per channel from the no-contact frames
   (:func:`~pipeline.streaming.plan.colour_gain_for`), in the normals' key; the reference is matched
   here, each chunk of frames as it is read.
2. **frames** (:func:`~pipeline.streaming.frames.run_frames`): what is missing is written into partial store files
   (:class:`pipeline.base.streamed.StreamedFile`) a chunk at a time by the one frame pipeline
   (:class:`pipeline.frame_pipeline.FramePipeline`: the solver's fast path where it has one,
   frames in parallel on ``threads`` threads), while the next chunk is read
   (:class:`pipeline.base.h5frames.H5Frames`) and the last one written and made durable on
   other threads. A killed run resumes from the last chunk its progress files record; a
   worker process or a Dask worker runs the same function on its own frame range.
3. **finish** (:func:`~pipeline.streaming.files.finish_stream`): the summaries (valid fraction, drift, errors against
   truth where the capture has it) go into the files' attributes, the files are renamed into
   place.

``--out`` folders get hard links to the store's files (symbolic links across file systems),
never a second copy (:func:`~pipeline.streaming.files.link_outputs`).

The modules, in that order: :mod:`~pipeline.streaming.job` (what is decided),
:mod:`~pipeline.streaming.inputs` (the files read), :mod:`~pipeline.streaming.plan`,
:mod:`~pipeline.streaming.frame_setup` (the frame pipeline), :mod:`~pipeline.streaming.frames`
and :mod:`~pipeline.streaming.writer`, :mod:`~pipeline.streaming.files` (opened, finished,
linked); :mod:`~pipeline.streaming.local` runs them all in one process.
"""

from pipeline.base.lazy import lazy_names

_WHERE = {"StreamJob": "job", "CONTACT_SPEC": "job", "LAZY_BYTES": "job", "read_capture": "inputs",
          "load_light_record": "inputs", "colour_matched_record": "inputs", "job_capture": "inputs", "job_frames": "inputs",
          "plan_stream": "plan", "colour_gain_for": "plan", "prepare": "frame_setup", "run_frames": "frames",
          "open_files": "files", "finish_stream": "files", "link_outputs": "files", "reconstruct_stream": "local"}
__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = list(_WHERE)
