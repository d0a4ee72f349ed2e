"""The operator's view: a read-only web page of the search and its targets, live and replayed."""
