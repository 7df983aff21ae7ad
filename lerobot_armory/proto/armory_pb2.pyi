from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Encoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    RAW: _ClassVar[Encoding]
    JPEG: _ClassVar[Encoding]
RAW: Encoding
JPEG: Encoding

class TensorSpec(_message.Message):
    __slots__ = ("name", "dtype", "shape")
    NAME_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    name: str
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, name: _Optional[str] = ..., dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ...) -> None: ...

class Tensor(_message.Message):
    __slots__ = ("name", "dtype", "shape", "data", "encoding")
    NAME_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    name: str
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    encoding: Encoding
    def __init__(self, name: _Optional[str] = ..., dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ..., encoding: _Optional[_Union[Encoding, str]] = ...) -> None: ...

class RegisterRequest(_message.Message):
    __slots__ = ("robot_id", "task", "fps", "h_min", "h_max", "weight", "tier", "features", "client_send_time", "auth_token", "policy_name")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    FPS_FIELD_NUMBER: _ClassVar[int]
    H_MIN_FIELD_NUMBER: _ClassVar[int]
    H_MAX_FIELD_NUMBER: _ClassVar[int]
    WEIGHT_FIELD_NUMBER: _ClassVar[int]
    TIER_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    CLIENT_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    AUTH_TOKEN_FIELD_NUMBER: _ClassVar[int]
    POLICY_NAME_FIELD_NUMBER: _ClassVar[int]
    robot_id: str
    task: str
    fps: float
    h_min: int
    h_max: int
    weight: float
    tier: str
    features: _containers.RepeatedCompositeFieldContainer[TensorSpec]
    client_send_time: float
    auth_token: str
    policy_name: str
    def __init__(self, robot_id: _Optional[str] = ..., task: _Optional[str] = ..., fps: _Optional[float] = ..., h_min: _Optional[int] = ..., h_max: _Optional[int] = ..., weight: _Optional[float] = ..., tier: _Optional[str] = ..., features: _Optional[_Iterable[_Union[TensorSpec, _Mapping]]] = ..., client_send_time: _Optional[float] = ..., auth_token: _Optional[str] = ..., policy_name: _Optional[str] = ...) -> None: ...

class RegisterResponse(_message.Message):
    __slots__ = ("session_id", "action_names", "chunk_size", "action_dim", "server_recv_time", "server_send_time", "policy", "expected_features", "max_message_bytes", "granted", "stream_address")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ACTION_NAMES_FIELD_NUMBER: _ClassVar[int]
    CHUNK_SIZE_FIELD_NUMBER: _ClassVar[int]
    ACTION_DIM_FIELD_NUMBER: _ClassVar[int]
    SERVER_RECV_TIME_FIELD_NUMBER: _ClassVar[int]
    SERVER_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    POLICY_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_FEATURES_FIELD_NUMBER: _ClassVar[int]
    MAX_MESSAGE_BYTES_FIELD_NUMBER: _ClassVar[int]
    GRANTED_FIELD_NUMBER: _ClassVar[int]
    STREAM_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    action_names: _containers.RepeatedScalarFieldContainer[str]
    chunk_size: int
    action_dim: int
    server_recv_time: float
    server_send_time: float
    policy: str
    expected_features: _containers.RepeatedCompositeFieldContainer[TensorSpec]
    max_message_bytes: int
    granted: Grant
    stream_address: str
    def __init__(self, session_id: _Optional[str] = ..., action_names: _Optional[_Iterable[str]] = ..., chunk_size: _Optional[int] = ..., action_dim: _Optional[int] = ..., server_recv_time: _Optional[float] = ..., server_send_time: _Optional[float] = ..., policy: _Optional[str] = ..., expected_features: _Optional[_Iterable[_Union[TensorSpec, _Mapping]]] = ..., max_message_bytes: _Optional[int] = ..., granted: _Optional[_Union[Grant, _Mapping]] = ..., stream_address: _Optional[str] = ...) -> None: ...

class Grant(_message.Message):
    __slots__ = ("weight", "tier", "fps", "h_min", "h_max", "max_device_share", "rule")
    WEIGHT_FIELD_NUMBER: _ClassVar[int]
    TIER_FIELD_NUMBER: _ClassVar[int]
    FPS_FIELD_NUMBER: _ClassVar[int]
    H_MIN_FIELD_NUMBER: _ClassVar[int]
    H_MAX_FIELD_NUMBER: _ClassVar[int]
    MAX_DEVICE_SHARE_FIELD_NUMBER: _ClassVar[int]
    RULE_FIELD_NUMBER: _ClassVar[int]
    weight: float
    tier: str
    fps: float
    h_min: int
    h_max: int
    max_device_share: float
    rule: str
    def __init__(self, weight: _Optional[float] = ..., tier: _Optional[str] = ..., fps: _Optional[float] = ..., h_min: _Optional[int] = ..., h_max: _Optional[int] = ..., max_device_share: _Optional[float] = ..., rule: _Optional[str] = ...) -> None: ...

class ClockSync(_message.Message):
    __slots__ = ("client_send_time", "server_recv_time", "server_send_time", "client_recv_time", "sync_id")
    CLIENT_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    SERVER_RECV_TIME_FIELD_NUMBER: _ClassVar[int]
    SERVER_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    CLIENT_RECV_TIME_FIELD_NUMBER: _ClassVar[int]
    SYNC_ID_FIELD_NUMBER: _ClassVar[int]
    client_send_time: float
    server_recv_time: float
    server_send_time: float
    client_recv_time: float
    sync_id: int
    def __init__(self, client_send_time: _Optional[float] = ..., server_recv_time: _Optional[float] = ..., server_send_time: _Optional[float] = ..., client_recv_time: _Optional[float] = ..., sync_id: _Optional[int] = ...) -> None: ...

class ClockSyncRequest(_message.Message):
    __slots__ = ("sync_id", "server_send_time")
    SYNC_ID_FIELD_NUMBER: _ClassVar[int]
    SERVER_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    sync_id: int
    server_send_time: float
    def __init__(self, sync_id: _Optional[int] = ..., server_send_time: _Optional[float] = ...) -> None: ...

class Observation(_message.Message):
    __slots__ = ("index", "capture_time", "tensors", "episode")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_TIME_FIELD_NUMBER: _ClassVar[int]
    TENSORS_FIELD_NUMBER: _ClassVar[int]
    EPISODE_FIELD_NUMBER: _ClassVar[int]
    index: int
    capture_time: float
    tensors: _containers.RepeatedCompositeFieldContainer[Tensor]
    episode: int
    def __init__(self, index: _Optional[int] = ..., capture_time: _Optional[float] = ..., tensors: _Optional[_Iterable[_Union[Tensor, _Mapping]]] = ..., episode: _Optional[int] = ...) -> None: ...

class ChunkReceipt(_message.Message):
    __slots__ = ("chunk_id", "arrival_time", "first_executed_index")
    CHUNK_ID_FIELD_NUMBER: _ClassVar[int]
    ARRIVAL_TIME_FIELD_NUMBER: _ClassVar[int]
    FIRST_EXECUTED_INDEX_FIELD_NUMBER: _ClassVar[int]
    chunk_id: int
    arrival_time: float
    first_executed_index: int
    def __init__(self, chunk_id: _Optional[int] = ..., arrival_time: _Optional[float] = ..., first_executed_index: _Optional[int] = ...) -> None: ...

class ExecutionReport(_message.Message):
    __slots__ = ("report_time", "index", "executed_steps", "starved_steps", "chunks")
    REPORT_TIME_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    EXECUTED_STEPS_FIELD_NUMBER: _ClassVar[int]
    STARVED_STEPS_FIELD_NUMBER: _ClassVar[int]
    CHUNKS_FIELD_NUMBER: _ClassVar[int]
    report_time: float
    index: int
    executed_steps: int
    starved_steps: int
    chunks: _containers.RepeatedCompositeFieldContainer[ChunkReceipt]
    def __init__(self, report_time: _Optional[float] = ..., index: _Optional[int] = ..., executed_steps: _Optional[int] = ..., starved_steps: _Optional[int] = ..., chunks: _Optional[_Iterable[_Union[ChunkReceipt, _Mapping]]] = ...) -> None: ...

class RobotMessage(_message.Message):
    __slots__ = ("observation", "report", "clock_sync")
    OBSERVATION_FIELD_NUMBER: _ClassVar[int]
    REPORT_FIELD_NUMBER: _ClassVar[int]
    CLOCK_SYNC_FIELD_NUMBER: _ClassVar[int]
    observation: Observation
    report: ExecutionReport
    clock_sync: ClockSync
    def __init__(self, observation: _Optional[_Union[Observation, _Mapping]] = ..., report: _Optional[_Union[ExecutionReport, _Mapping]] = ..., clock_sync: _Optional[_Union[ClockSync, _Mapping]] = ...) -> None: ...

class ActionChunk(_message.Message):
    __slots__ = ("chunk_id", "i_start", "actions", "server_send_time", "obs_capture_time", "episode")
    CHUNK_ID_FIELD_NUMBER: _ClassVar[int]
    I_START_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    SERVER_SEND_TIME_FIELD_NUMBER: _ClassVar[int]
    OBS_CAPTURE_TIME_FIELD_NUMBER: _ClassVar[int]
    EPISODE_FIELD_NUMBER: _ClassVar[int]
    chunk_id: int
    i_start: int
    actions: Tensor
    server_send_time: float
    obs_capture_time: float
    episode: int
    def __init__(self, chunk_id: _Optional[int] = ..., i_start: _Optional[int] = ..., actions: _Optional[_Union[Tensor, _Mapping]] = ..., server_send_time: _Optional[float] = ..., obs_capture_time: _Optional[float] = ..., episode: _Optional[int] = ...) -> None: ...

class Notice(_message.Message):
    __slots__ = ("kind", "message", "index")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        INFO: _ClassVar[Notice.Kind]
        REJECTED_OBSERVATION: _ClassVar[Notice.Kind]
        REJECTED_REPORT: _ClassVar[Notice.Kind]
        INFERENCE_FAILED: _ClassVar[Notice.Kind]
        SHUTDOWN: _ClassVar[Notice.Kind]
        DROPPED: _ClassVar[Notice.Kind]
        CLOCK: _ClassVar[Notice.Kind]
        MOVED: _ClassVar[Notice.Kind]
    INFO: Notice.Kind
    REJECTED_OBSERVATION: Notice.Kind
    REJECTED_REPORT: Notice.Kind
    INFERENCE_FAILED: Notice.Kind
    SHUTDOWN: Notice.Kind
    DROPPED: Notice.Kind
    CLOCK: Notice.Kind
    MOVED: Notice.Kind
    KIND_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    kind: Notice.Kind
    message: str
    index: int
    def __init__(self, kind: _Optional[_Union[Notice.Kind, str]] = ..., message: _Optional[str] = ..., index: _Optional[int] = ...) -> None: ...

class ServerMessage(_message.Message):
    __slots__ = ("chunk", "notice", "sync_request")
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    NOTICE_FIELD_NUMBER: _ClassVar[int]
    SYNC_REQUEST_FIELD_NUMBER: _ClassVar[int]
    chunk: ActionChunk
    notice: Notice
    sync_request: ClockSyncRequest
    def __init__(self, chunk: _Optional[_Union[ActionChunk, _Mapping]] = ..., notice: _Optional[_Union[Notice, _Mapping]] = ..., sync_request: _Optional[_Union[ClockSyncRequest, _Mapping]] = ...) -> None: ...

class SwapRequest(_message.Message):
    __slots__ = ("policy_path", "overrides", "drain", "policy_name")
    POLICY_PATH_FIELD_NUMBER: _ClassVar[int]
    OVERRIDES_FIELD_NUMBER: _ClassVar[int]
    DRAIN_FIELD_NUMBER: _ClassVar[int]
    POLICY_NAME_FIELD_NUMBER: _ClassVar[int]
    policy_path: str
    overrides: _containers.RepeatedScalarFieldContainer[str]
    drain: bool
    policy_name: str
    def __init__(self, policy_path: _Optional[str] = ..., overrides: _Optional[_Iterable[str]] = ..., drain: _Optional[bool] = ..., policy_name: _Optional[str] = ...) -> None: ...

class SwapResponse(_message.Message):
    __slots__ = ("result", "message", "old_path", "new_path", "seconds")
    RESULT_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    OLD_PATH_FIELD_NUMBER: _ClassVar[int]
    NEW_PATH_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    result: str
    message: str
    old_path: str
    new_path: str
    seconds: float
    def __init__(self, result: _Optional[str] = ..., message: _Optional[str] = ..., old_path: _Optional[str] = ..., new_path: _Optional[str] = ..., seconds: _Optional[float] = ...) -> None: ...

class AdminStatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class AdminStatusResponse(_message.Message):
    __slots__ = ("policy_path", "policy", "robots", "swaps_ok", "swaps_refused", "swaps_failed", "status_line", "replicas")
    POLICY_PATH_FIELD_NUMBER: _ClassVar[int]
    POLICY_FIELD_NUMBER: _ClassVar[int]
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    SWAPS_OK_FIELD_NUMBER: _ClassVar[int]
    SWAPS_REFUSED_FIELD_NUMBER: _ClassVar[int]
    SWAPS_FAILED_FIELD_NUMBER: _ClassVar[int]
    STATUS_LINE_FIELD_NUMBER: _ClassVar[int]
    REPLICAS_FIELD_NUMBER: _ClassVar[int]
    policy_path: str
    policy: str
    robots: int
    swaps_ok: int
    swaps_refused: int
    swaps_failed: int
    status_line: str
    replicas: _containers.RepeatedCompositeFieldContainer[ReplicaStatus]
    def __init__(self, policy_path: _Optional[str] = ..., policy: _Optional[str] = ..., robots: _Optional[int] = ..., swaps_ok: _Optional[int] = ..., swaps_refused: _Optional[int] = ..., swaps_failed: _Optional[int] = ..., status_line: _Optional[str] = ..., replicas: _Optional[_Iterable[_Union[ReplicaStatus, _Mapping]]] = ...) -> None: ...

class ReplicaStatus(_message.Message):
    __slots__ = ("replica_id", "up", "policy_path", "robots", "swaps_ok", "swaps_refused", "swaps_failed")
    REPLICA_ID_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    POLICY_PATH_FIELD_NUMBER: _ClassVar[int]
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    SWAPS_OK_FIELD_NUMBER: _ClassVar[int]
    SWAPS_REFUSED_FIELD_NUMBER: _ClassVar[int]
    SWAPS_FAILED_FIELD_NUMBER: _ClassVar[int]
    replica_id: str
    up: bool
    policy_path: str
    robots: int
    swaps_ok: int
    swaps_refused: int
    swaps_failed: int
    def __init__(self, replica_id: _Optional[str] = ..., up: _Optional[bool] = ..., policy_path: _Optional[str] = ..., robots: _Optional[int] = ..., swaps_ok: _Optional[int] = ..., swaps_refused: _Optional[int] = ..., swaps_failed: _Optional[int] = ...) -> None: ...
