"""HTTP routes: ``verifications`` (one pair), ``batches`` (many pairs), ``limits``, ``health``."""
