"""One module per `matcap` sub-command; each exposes ``register(subparsers)``."""
