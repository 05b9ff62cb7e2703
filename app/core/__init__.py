"""Gateway internals: settings, errors as problem+json, security, uploads."""
