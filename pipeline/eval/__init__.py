"""Evaluation: the checks of a problem before any work, every reported number (alignment, ground-truth errors,
the field's registration metrics, the pose covariance), deviation maps and the interactive 3D view."""
