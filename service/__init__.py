"""agilegs.service: the NBV server, its maths core (agilegs.service.nbv), mapper, benchmark."""
