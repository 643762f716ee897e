"""The HTTP service: FastAPI + onnxruntime + Open3D, never torch.

``pranet-serve`` (``cli.py``) verifies the model and starts uvicorn on ``app.create_app``; the
lifespan loads the model once per worker (``state.py``); ``routes/`` holds one router per resource;
``registration.py`` turns a request body into ``core.pipeline.register`` and back into the
response of ``schemas.py``. Configuration: ``settings.py`` (``PRANET_*`` environment variables).
"""
