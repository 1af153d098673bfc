"""MATLAB captures (``.mat``, the version 4 to 7.2 files MATLAB's ``save``
writes by default; docs/inputs.md, "MATLAB captures"): ``reader``, over
``scipy.io.loadmat``. rotcal writes none."""
