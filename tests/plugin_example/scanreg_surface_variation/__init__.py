"""A separate package that adds a salience measure to scanreg: one class, registered through the ``scanreg.stages``
entry point (see its ``.dist-info/entry_points.txt``), and one YAML (``conf/salience/surface_variation.yaml``).
The example of the documentation's "Extending scanreg" page; ``tests/test_plugin.py`` runs it."""

import numpy as np

from scanreg.stages.registry import SALIENCE
from scanreg.stages.salience import EigenSalience


@SALIENCE.register("surface_variation")
class SurfaceVariation(EigenSalience):
    """Surface variation l1 / (l1 + l2 + l3) of the point covariance C_p (Pauly, Gross & Kobbelt 2002): 0 on a
    plane, up to 1/3 where the surface bends equally in every direction; keypoints are its maxima."""

    def salience(self, lam: np.ndarray) -> np.ndarray:
        return lam[:, 0] / np.maximum(lam.sum(axis=1), 1e-300)
