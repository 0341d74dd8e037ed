"""Applications built on the library, behind ``svr demo`` and ``svr loss-demo``.

:mod:`svr.apps.demo` runs the end-to-end demonstration (simulate a case, reconstruct it with each
registration, score and plot the results); :mod:`svr.apps.loss_demo` compares the SE(3) loss with
its baselines on a toy regression. They sit on top of the packages, beside :mod:`svr.cli`: the
core, :mod:`svr.sampling`, :mod:`svr.models` and :mod:`svr.reconstruction` never import them.
"""
