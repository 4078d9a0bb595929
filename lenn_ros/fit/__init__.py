"""Model building: ``lenn-ros fit``, from a recorded log to a model the identifier node runs.

- :mod:`.build`: the single-output fit (families, selection, refinement; the report and outputs);
- :mod:`.mimo`: several inputs and outputs, one MISO model per output;
- :mod:`.bag`: a bag's samples as the identifier node pairs them;
- :mod:`.data`: the loaded record and ``FitError``, shared by the readers;
- :mod:`.families`: the dictionaries of terms (polynomial, hinge, increment, ...);
- :mod:`.selection`: term selection by simulation (the LeNN's FROLS);
- :mod:`.refinement`: weights refined on simulation error;
- :mod:`.training`: epochs for the gradient-trained models (SGD LeNN, MLP).

Nothing is imported here (import the module you need), so loading one of them loads no other.
"""
