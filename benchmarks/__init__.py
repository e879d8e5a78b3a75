"""The benchmarks of monai-rigidreg, by area; run each as a module from the repository root
(``python -m benchmarks.<area>.<script> --help``). Method, areas and result naming: ``benchmarks/README.md``."""
