"""Networks: vertex encoders (PointNet, PointNet v2), texture encoders (HiDDeN CNN, U-Net), decoders."""

from .decoders import HiddenDecoder, ResidualCNNDecoder, SimpleCNNDecoder
from .texture_encoders import HiddenTextureEncoder, UNetTextureEncoder
from .vertex_encoders import PointNetVertexEncoder
from .watermark import STRATEGIES, ModelConfig, WatermarkModel

__all__ = ["HiddenDecoder", "ResidualCNNDecoder", "SimpleCNNDecoder", "HiddenTextureEncoder",
           "UNetTextureEncoder", "PointNetVertexEncoder", "ModelConfig", "WatermarkModel", "STRATEGIES"]
