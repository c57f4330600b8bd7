"""OctoPrint's face of the print server: its REST API, push socket and app keys."""
