"""Plain per-image reference implementation of ALGORITHM.md (NumPy + OpenCV).

One module per stage, named as in the tensor path: :mod:`.sky` (section 1), :mod:`.color`
(2), :mod:`.vegetation` (3-4), :mod:`.hough` (5), :mod:`.vanishing` (6), :mod:`.ransac` (7);
:mod:`.pipeline` composes them; :mod:`.tracking` is video mode (section 8), :mod:`.lattice` the
improved mode (11) and :mod:`.lattice_tracking` its video mode (11.7). Readable first: loops
where they read best.
"""

from torchrow.reference import color, hough, ransac, sky, vanishing, vegetation
from torchrow.reference.lattice_tracking import LatticeSequenceState
from torchrow.reference.pipeline import detect, prepare
from torchrow.reference.tracking import SequenceState, Tracker

__all__ = ["detect", "prepare", "Tracker", "SequenceState", "LatticeSequenceState",
           "sky", "color", "vegetation", "hough", "vanishing", "ransac"]
