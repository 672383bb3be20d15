"""How a call finds its path and checks it: the machinery every op shares.

* ``omp_wait``: how long idle OpenMP threads spin (chosen before torch is imported: ``modi_ext/__init__.py``);
* ``loader``: the compiled extension (``HAS_EXT``, ``LOAD_ERROR``; not loaded under a torch other than its build's)
  and the path asked for (``MODI_EXT_IMPL``);
* ``kernels``: the raw kernels by name (a test hook), which device types a build covers, one key per device;
* ``eager``: the eager fast path (registered kernels called through plain ``autograd.Function``s);
* ``dispatch``: the per-call choice between kernels, dense form and reference, and ``dispatch_report()``;
* ``payload``: one shape list that launches every kernel instantiation, with its float64 oracle;
* ``selfcheck``: the kernels' first-use check on a (device, dtype), on the payload.

The first five sit below the ops; ``payload`` and ``selfcheck`` above them (they run the ops' references, and the
demod op), so ``dispatch`` is handed the self-check by ``modi_ext/__init__.py`` instead of importing it.  This
``__init__`` imports nothing.
"""
