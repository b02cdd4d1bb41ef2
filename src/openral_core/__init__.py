"""openral contracts: the typed models, enums and errors every stage speaks. No I/O."""

from openral_core.actions import Action, ControlMode, SafetyEnvelope, SafetyMode
from openral_core.environment import (
    DeadlineOverrunPolicy,
    FaultPolicy,
    HalConfig,
    RealtimeConfig,
    RobotEnvironment,
    SafetyConfig,
    SensorReaderBackend,
    SensorReaderConfig,
    TaskSpec,
    VLASpec,
)
from openral_core.errors import (
    ROSConfigError,
    ROSDeadlineMissed,
    ROSDependencyMissing,
    ROSError,
    ROSEStopRequested,
    ROSHardwareError,
    ROSLicenseError,
    ROSPerceptionStale,
    ROSRuntimeError,
    ROSSafetyViolation,
    ROSSkillError,
    ROSStopRequested,
    ROSSyncError,
)
from openral_core.frames import FrameEncoding, SensorFrame
from openral_core.results import RunResult, TickResult
from openral_core.robot import JointKind, JointSpec, ModelRef, RobotManifest
from openral_core.skills import RSkillInfo, RSkillState
from openral_core.world import ComponentDiagnostics, JointState, Pose6D, WorldState

__all__ = [
    "Action",
    "ComponentDiagnostics",
    "ControlMode",
    "DeadlineOverrunPolicy",
    "FaultPolicy",
    "FrameEncoding",
    "HalConfig",
    "JointKind",
    "JointSpec",
    "JointState",
    "ModelRef",
    "Pose6D",
    "ROSConfigError",
    "ROSDeadlineMissed",
    "ROSDependencyMissing",
    "ROSEStopRequested",
    "ROSError",
    "ROSHardwareError",
    "ROSLicenseError",
    "ROSPerceptionStale",
    "ROSRuntimeError",
    "ROSSafetyViolation",
    "ROSSkillError",
    "ROSStopRequested",
    "ROSSyncError",
    "RSkillInfo",
    "RSkillState",
    "RealtimeConfig",
    "RobotEnvironment",
    "RobotManifest",
    "RunResult",
    "SafetyConfig",
    "SafetyEnvelope",
    "SafetyMode",
    "SensorFrame",
    "SensorReaderBackend",
    "SensorReaderConfig",
    "TaskSpec",
    "TickResult",
    "VLASpec",
    "WorldState",
]
