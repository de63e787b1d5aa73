"""An rclpy node of its own, spun by its own executor in its own thread: what a device backend
that talks ROS (``ros_topics``) runs beside the driver's executor and the loop thread, and
what ``haptic-topology replay`` publishes and listens with."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


class NodeThread:
    """Node ``name`` in the process's rclpy context (or, where rclpy is not initialised or
    ``own_context`` is set: a test, a tool, a context of its own, shut down by
    :meth:`close`), without the
    process's ROS arguments (the driver's remappings and parameters do not apply to it);
    ``setup(node)`` creates its subscriptions and publishers before the thread
    ``thread_name`` starts spinning it on an :class:`~rclpy.experimental.EventsExecutor`;
    ``namespace``: the node's (default: the root).
    On any error in the set-up everything made so far is destroyed again."""

    def __init__(self, name: str, thread_name: str,
                 setup: Callable[[Node], None] = lambda node: None,
                 own_context: bool = False, namespace: str = '') -> None:
        from rclpy.experimental import EventsExecutor

        if rclpy.ok() and not own_context:
            self.context, self._own_context = rclpy.get_default_context(), False
        else:
            self.context, self._own_context = Context(), True
            rclpy.init(context=self.context)
        self._stop = threading.Event()
        self._node: Node | None = None
        self._executor: Any = None
        self.thread: threading.Thread | None = None
        try:
            self._node = rclpy.create_node(name, context=self.context, namespace=namespace,
                                          use_global_arguments=False,
                                          start_parameter_services=False)
            setup(self._node)
            self._executor = EventsExecutor(context=self.context)
            self._executor.add_node(self._node)
            self.thread = threading.Thread(target=self._spin, name=thread_name, daemon=True)
            self.thread.start()
        except BaseException:
            self.close()
            raise

    @property
    def node(self) -> Node:
        """The node (until :meth:`close`)."""
        if self._node is None:
            raise RuntimeError('NodeThread: the node is closed')
        return self._node

    def _spin(self) -> None:
        # spin_once with a timeout: spin() of this rclpy build's EventsExecutor burns a core
        # (haptic_topology.nodes.runtime).
        executor = self._executor
        while not self._stop.is_set():
            try:
                executor.spin_once(timeout_sec=0.05)
            except (ExternalShutdownException, RuntimeError):
                # rclpy's shutdown under a running spin (RCLError is a RuntimeError): the
                # process is ending; anything else is a bug and is raised.
                if self._stop.is_set() or not self.context_ok():
                    return
                raise

    def context_ok(self) -> bool:
        """Whether the node's rclpy context is still up (the process is not shutting down)."""
        return self.context.ok()

    def alive(self) -> bool:
        """Whether the spinning thread still runs."""
        return self.thread is not None and self.thread.is_alive()

    def close(self) -> None:
        """Stop the thread, destroy the executor and the node (and the context made here)."""
        self._stop.set()
        if self.thread is not None:
            self.thread.join(timeout=2.0)
        self.thread = None
        if self._executor is not None:
            self._executor.shutdown(timeout_sec=1.0)
        self._executor = None
        if self._node is not None:
            self._node.destroy_node()
        self._node = None
        if self._own_context:
            rclpy.try_shutdown(context=self.context)
        self._own_context = False
