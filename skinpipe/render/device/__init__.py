"""The machinery below the algorithms: which OpenCL device runs the kernels and why
(choice), the runtimes skinpipe installs (runtimes), programs built and kernels
launched (programs), host and device memory (memory, huge_pages)."""
