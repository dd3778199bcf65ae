"""Device interfaces and real drivers. Each device kind has one abstract class; back-ends are chosen by URL
through :mod:`lapreco_hil.registry` and imported lazily."""
