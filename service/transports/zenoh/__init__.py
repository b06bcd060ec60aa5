"""The Zenoh transport: queryables, subscriptions and the decision publication
(:mod:`.adapter`), and Zenoh's own TLS, authentication and access control (:mod:`.security`)."""
