"""The network lab: the three roles in network namespaces of their own, links shaped."""
