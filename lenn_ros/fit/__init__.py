"""Model building: ``lenn-ros fit``, from a recorded log to a model the identifier node runs.

Any number of inputs and outputs (one MISO model per output); a module per concern:

- :mod:`.command`: the command line's front-end (read, fit, write, plot, report);
- :mod:`.load`: reading a CSV file or a bag into one record; :mod:`.bag`: a bag's samples,
  paired as the node pairs them; :mod:`.data`: the record and ``FitError``, shared by the readers;
- :mod:`.procedure`: ``fit()``, the procedure (each output's views, its selection and
  refinement, the scoring, the result); :mod:`.schedule`: what of it runs side by side
  on the cores; :mod:`.delay`, :mod:`.signs`, :mod:`.rest`, :mod:`.memory`: its steps
  for dead times, outputs read as |y|, long rest and logs longer than memory;
- :mod:`.families`: the model families, one module each, and their registry;
- :mod:`.selection`: term selection by simulation (the LeNN's FROLS), over
  :mod:`.termmodel` (the model: Layout, TermModel, its compiled free run), :mod:`.record`
  (the training samples, their runs and blocks), :mod:`.regression` (FROLS's ranking,
  each block's least squares) and :mod:`.soundness` (the in-sample and shuffled-input checks);
- :mod:`.refinement`: weights refined on simulation error; :mod:`.training`: epochs for the
  gradient-trained models (SGD LeNN, MLP);
- :mod:`.scoring`: the test part's figures and bands; :mod:`.export`: the identifier the
  node runs and the files ``-o`` writes; :mod:`.result`: what ``fit()`` returns
  (``FitResult``; its ``as_dict()`` is the JSON report); :mod:`.report`: the text report.

Nothing is imported here: importing one module loads only what that module needs.
"""
