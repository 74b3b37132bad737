"""Flags and predictions -> a new model revision: ``fleetbrake close-loop``
(:func:`fleetbrake.closeloop.loop.close_loop`) runs its phases in order, each a module handing
the next a typed result: :mod:`~fleetbrake.closeloop.evidence` (residual and evidence),
:mod:`~fleetbrake.closeloop.candidates` (candidate families), :mod:`~fleetbrake.closeloop.fit`,
:mod:`~fleetbrake.closeloop.selection`, :mod:`~fleetbrake.closeloop.verdict`,
:mod:`~fleetbrake.closeloop.revision` (the new revision) and :mod:`~fleetbrake.closeloop.report`
(the typed report, rendered as Markdown by :mod:`~fleetbrake.closeloop.markdown`). Below them:
the configuration (:mod:`~fleetbrake.closeloop.config`), the statistics
(:mod:`~fleetbrake.closeloop.stats`), the fit events as arrays
(:mod:`~fleetbrake.closeloop.fitdata`, :mod:`~fleetbrake.closeloop.spans`), the least-squares
fit (:mod:`~fleetbrake.closeloop.leastsquares`), the intervals' numerical and input terms
(:mod:`~fleetbrake.closeloop.terms`) and where the work runs
(:mod:`~fleetbrake.closeloop.workers`)."""
