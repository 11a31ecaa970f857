"""What stands between the network and the routes: the HTTP server with its connection
cap (:mod:`.server`), the request guard (:mod:`.guard`: host, token, size, JSON), the
event streams' gate (:mod:`.streams`) and the threads kept for control (:mod:`.control`)."""
