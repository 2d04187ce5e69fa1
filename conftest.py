# pytest puts this file's folder, the repository root, on sys.path: the tests import `bench.<name>`.
