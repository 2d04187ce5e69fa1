"""``lerobot-cnmp-serve``: LeRobot's async-inference ``PolicyServer`` with CNMP accepted.

LeRobot's server accepts only the policy types in ``lerobot.async_inference.constants.SUPPORTED_POLICIES`` and
loads no plugins. This command imports the plugin (registering ``cnmp``), adds ``cnmp`` to that list and runs
LeRobot's own server, with one addition: each observation's timestep reaches ``predict_action_chunk``, so a
chunk starts at the phase of the step its observation was taken at (the client numbers its observations and
merges chunks by timestep; without this the phase clock would run one chunk ahead per request).

    lerobot-cnmp-serve --host=127.0.0.1 --port=8080           # same flags as LeRobot's policy server
    python -m lerobot.async_inference.robot_client --robot.type=so101_follower ... \\
        --policy_type=cnmp --pretrained_name_or_path=<ckpt> --actions_per_chunk=30 --server_address=127.0.0.1:8080

The conditions of a checkpoint (``conditions`` in its config.json) apply; the client cannot send them.
"""

from __future__ import annotations

import logging
from concurrent import futures
from pprint import pformat

POLICY_TYPE = "cnmp"


def accept_cnmp() -> None:
    """Register CNMP and add it to LeRobot's list of server policies (the list object the server reads)."""
    import lerobot_cnmp  # noqa: F401  (registers the policy type)
    from lerobot.async_inference import constants

    if POLICY_TYPE not in constants.SUPPORTED_POLICIES:
        constants.SUPPORTED_POLICIES.append(POLICY_TYPE)


def make_server_class():
    from lerobot.async_inference.policy_server import PolicyServer

    class CNMPPolicyServer(PolicyServer):
        """LeRobot's PolicyServer; CNMP chunks start at their observation's timestep."""

        def _predict_action_chunk(self, observation_t):
            self._cnmp_timestep = observation_t.get_timestep()
            return super()._predict_action_chunk(observation_t)

        def _get_action_chunk(self, observation):
            if getattr(self.policy, "name", None) != POLICY_TYPE:
                return super()._get_action_chunk(observation)
            chunk = self.policy.predict_action_chunk(observation, n_steps=self.actions_per_chunk,
                                                     timestep=getattr(self, "_cnmp_timestep", None))
            return chunk[:, : self.actions_per_chunk, :]

    return CNMPPolicyServer


def start_server(cfg):
    """Start the gRPC server as LeRobot's ``serve`` does, with :func:`make_server_class`'s servicer; returns
    (grpc server, servicer). The caller waits or stops it."""
    import grpc
    from lerobot.transport import services_pb2_grpc

    accept_cnmp()
    servicer = make_server_class()(cfg)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    services_pb2_grpc.add_AsyncInferenceServicer_to_server(servicer, server)
    server.add_insecure_port(f"{cfg.host}:{cfg.port}")
    server.start()
    servicer.logger.info(f"PolicyServer (with CNMP) started on {cfg.host}:{cfg.port}")
    return server, servicer


def main() -> None:
    import draccus
    from lerobot.async_inference.configs import PolicyServerConfig

    accept_cnmp()

    @draccus.wrap()
    def serve(cfg: PolicyServerConfig):
        logging.info(pformat(cfg))
        server, servicer = start_server(cfg)
        server.wait_for_termination()
        servicer.logger.info("Server terminated")

    serve()


if __name__ == "__main__":
    main()
