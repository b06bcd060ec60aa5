"""The Zenoh transport: queryables, subscriptions and the decision publication
(:mod:`.adapter`), Zenoh's own TLS, authentication and access control (:mod:`.security`), and
the cluster of instances joined over Zenoh, each session served by one of them
(:mod:`.cluster`)."""
