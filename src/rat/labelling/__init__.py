"""People label the target behaviour: a labelling page that feeds PEBBLE and RAT runs.

- :class:`~rat.labelling.web.WebLabeller`: a :class:`~rat.preferences.labeller.Labeller` that, at
  each query round, publishes the round's queries in the run's label store, films their segments,
  and waits until a person has answered them (or a timeout passes).
- :func:`~rat.labelling.server.create_app`: the labelling page and its HTTP API (FastAPI), served
  from a label store; every answer is one durable transaction in that store.

The store is the only state: a server restarted, or a run killed while it waits, loses nothing.
"""

from rat.labelling.web import WebLabeller, WebLabellingConfig

__all__ = ["WebLabeller", "WebLabellingConfig"]
