"""The torch-free inference engine: the onnxruntime reward model, the Open3D ICP and the registrar built from one
``RegistrationConfig``. The service, ``pranet-eval``, ``pranet-bench`` and the scripts all register through it."""
