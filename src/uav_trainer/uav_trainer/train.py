def main(args=None):
    raise SystemExit("not implemented yet")
